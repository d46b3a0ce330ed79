// Test driver: FramePlayout (DimgestorPlayout.h) on recorded frames and a schedule of arrivals and samples.
// usage: playout_check FOLDER SCHEDULE   (schedule lines: "push K T" | "sample T" | "delay S")
// Prints one JSON line per sample; tests/test_clients_playout.py compares the three clients' outputs.
#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <sstream>
#include <string>
#include <vector>

#include "../DimgestorPlayout.h"

namespace fs = std::filesystem;
using namespace dimgestor;

static std::string N(double v) { char b[40]; std::snprintf(b, sizeof b, "%.17g", v); return b; }

int main(int argc, char** argv) {
  if (argc != 3) { std::fprintf(stderr, "usage: playout_check FOLDER SCHEDULE\n"); return 2; }
  std::vector<fs::path> files;
  for (const auto& e : fs::directory_iterator(argv[1])) files.push_back(e.path());
  std::sort(files.begin(), files.end());
  std::vector<Frame> frames;
  for (const fs::path& p : files) {
    std::ifstream in(p, std::ios::binary);
    std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    Message m;
    std::string error;
    if (p.extension() == ".bin") {
      if (DecodeBinaryFrame(reinterpret_cast<const uint8_t*>(bytes.data()), bytes.size(), m.frame, error))
        frames.push_back(m.frame);
    } else if (ParseMessage(bytes, m, error) && m.type == MessageType::Frame) {
      frames.push_back(m.frame);
    }
  }
  FramePlayout playout;
  std::ifstream schedule(argv[2]);
  std::string line;
  while (std::getline(schedule, line)) {
    std::istringstream words(line);
    words.imbue(std::locale::classic());
    std::string op;
    words >> op;
    if (op == "delay") {
      words >> playout.delay_s;
    } else if (op == "push") {
      size_t k;
      double t;
      words >> k >> t;
      playout.Push(frames.at(k), t);
    } else if (op == "sample") {
      double t;
      words >> t;
      Frame s;
      if (!playout.Sample(t, s)) { std::printf("null\n"); continue; }
      std::string out = "{\"index\":" + std::to_string(s.index) + ",\"pts\":" + N(s.pts) + ",\"root\":[" + N(s.root.x) +
                        "," + N(s.root.y) + "," + N(s.root.z) + "],\"rotations\":[";
      for (size_t j = 0; j < s.rotations.size(); ++j) {
        const Quat& q = s.rotations[j];
        out += (j ? ",[" : "[") + N(q.w) + "," + N(q.x) + "," + N(q.y) + "," + N(q.z) + "]";
      }
      std::printf("%s]}\n", out.c_str());
    }
  }
  std::fprintf(stderr, "reanchors %d\n", playout.reanchors);
  return 0;
}
