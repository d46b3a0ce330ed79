// Test driver: the server's messages, decoded by ParseMessage, driving AudioFlow (DimgestorAudioFlow.h) the way
// UDimgestorComponent does (slow_down -> SlowDown, Resume -> Resume + a pending audio_end), on a script.
// usage: flow_check MAX_HELD_S SCRIPT   (lines: "message JSON" | "chunk ID SECONDS" | "end")
// Prints one JSON line per line of the script; tests/test_clients_unreal.py checks them.
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "../DimgestorAudioFlow.h"
#include "../DimgestorProtocol.h"

using namespace dimgestor;

static std::string N(double v) { char b[40]; std::snprintf(b, sizeof b, "%.17g", v); return b; }

int main(int argc, char** argv) {
  if (argc != 3) { std::fprintf(stderr, "usage: flow_check MAX_HELD_S SCRIPT\n"); return 2; }
  AudioFlow flow(std::atof(argv[1]));
  std::ifstream in(argv[2]);
  std::string line;
  while (std::getline(in, line)) {
    if (line.empty()) continue;
    const size_t sp = line.find(' ');
    const std::string op = line.substr(0, sp), rest = sp == std::string::npos ? "" : line.substr(sp + 1);
    std::vector<AudioFlow::Chunk> sent;
    std::string type, code;
    double backlog = -1;
    bool end_now = false;
    if (op == "message") {
      Message m;
      std::string error;
      if (!ParseMessage(rest, m, error)) { std::fprintf(stderr, "%s\n", error.c_str()); return 1; }
      type = m.type_name;
      if (m.type == MessageType::Error) {
        code = m.error_code;
        if (code == "slow_down") flow.SlowDown();
      } else if (m.type == MessageType::Resume) {
        backlog = m.resume_backlog_s;
        sent = flow.Resume();
        end_now = flow.TakeEndPending();
      }
    } else if (op == "chunk") {
      std::istringstream w(rest);
      std::string id;
      double seconds = 0;
      w >> id >> seconds;
      sent = flow.Offer(AudioFlow::Chunk(id.begin(), id.end()), seconds);
    } else if (op == "end") {
      end_now = flow.End();
    }
    std::string ids;
    for (const auto& c : sent) ids += (ids.empty() ? "\"" : ",\"") + std::string(c.begin(), c.end()) + "\"";
    std::printf("{\"event\":\"%s\",\"type\":\"%s\",\"code\":\"%s\",\"backlog_s\":%s,\"sent\":[%s],\"end_now\":%s,"
                "\"paused\":%s,\"held_s\":%s,\"dropped_s\":%s,\"dropped_chunks\":%lld,\"pauses\":%lld,\"resumes\":%lld}\n",
                op.c_str(), type.c_str(), code.c_str(), N(backlog).c_str(), ids.c_str(), end_now ? "true" : "false",
                flow.paused() ? "true" : "false", N(flow.held_s()).c_str(), N(flow.dropped_s()).c_str(),
                (long long)flow.dropped_chunks(), (long long)flow.pauses(), (long long)flow.resumes());
  }
  return 0;
}
