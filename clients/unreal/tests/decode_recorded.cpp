// Test driver: decode recorded server messages (NNNNNN.json / NNNNNN.bin in a folder, as saved by
// clients/python/client.py --save) with DimgestorProtocol and print one JSON line per message.
// tests/test_clients_unreal.py compares the output with what the server sent.
#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>
#include <vector>

#include "../DimgestorProtocol.h"

namespace fs = std::filesystem;
using namespace dimgestor;

static std::string N(double v) { char b[40]; std::snprintf(b, sizeof b, "%.17g", v); return b; }
static std::string V(const Vec3& v) { return "[" + N(v.x) + "," + N(v.y) + "," + N(v.z) + "]"; }
static std::string Q(const Quat& q) { return "[" + N(q.w) + "," + N(q.x) + "," + N(q.y) + "," + N(q.z) + "]"; }
template <typename F>
static std::string Qs(const std::vector<Quat>& qs, F f) {
  std::string s = "[";
  for (size_t i = 0; i < qs.size(); ++i) s += (i ? "," : "") + Q(f(qs[i]));
  return s + "]";
}
static std::string Escape(const std::string& s) {
  std::string o;
  for (char c : s) { if (c == '"' || c == '\\') o += '\\'; o += c; }
  return o;
}

int main(int argc, char** argv) {
  if (argc != 2) { std::fprintf(stderr, "usage: decode_recorded FOLDER\n"); return 2; }
  std::vector<fs::path> files;
  for (const auto& e : fs::directory_iterator(argv[1])) files.push_back(e.path());
  std::sort(files.begin(), files.end());
  Skeleton skeleton;
  Hello hello;  // the binary frames' layout once a hello was read (its channels: the last `channels` message's)
  bool have_hello = false;
  for (const fs::path& path : files) {
    std::ifstream in(path, std::ios::binary);
    std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    std::string error;
    Message m;
    bool ok;
    if (path.extension() == ".bin") {
      m.type = MessageType::Frame;
      m.type_name = "frame";
      ok = DecodeBinaryFrame(reinterpret_cast<const uint8_t*>(bytes.data()), bytes.size(), m.frame, error,
                             have_hello ? &hello : nullptr);
    } else if (path.extension() == ".json") {
      ok = ParseMessage(bytes, m, error);
    } else {
      continue;
    }
    std::string line = "{\"file\":\"" + path.filename().string() + "\"";
    if (!ok) { std::printf("%s,\"error\":\"%s\"}\n", line.c_str(), Escape(error).c_str()); continue; }
    line += ",\"type\":\"" + m.type_name + "\"";
    if (m.type == MessageType::Hello) {
      skeleton = m.hello.skeleton;
      hello = m.hello;
      have_hello = true;
      line += ",\"joints\":" + std::to_string(skeleton.joints.size()) + ",\"humanoid\":" +
              std::to_string(m.hello.humanoid.size()) + ",\"fps\":" + N(m.hello.fps) + ",\"unit_to_m\":" +
              N(skeleton.unit_to_m) + ",\"audio_rate\":" + std::to_string(m.hello.audio_rate) +
              ",\"offset_last\":" + V(skeleton.offsets.back());
      if (m.hello.face.present) {
        auto strings = [](const std::vector<std::string>& v) {
          std::string o = "[";
          for (size_t i = 0; i < v.size(); ++i) o += (i ? ",\"" : "\"") + Escape(v[i]) + "\"";
          return o + "]";
        };
        line += ",\"face\":{\"names\":\"" + Escape(m.hello.face.names) + "\",\"sets\":" + strings(m.hello.face.sets) +
                ",\"labels\":" + strings(m.hello.face.labels) + "}";
      }
    } else if (m.type == MessageType::Channels) {
      if (have_hello) hello.channels = m.channels;
      line += ",\"layout\":[";
      for (size_t i = 0; i < m.channels.size(); ++i)
        line += (i ? ",[\"" : "[\"") + Escape(m.channels[i].name) + "\"," + std::to_string(m.channels[i].size) + "," +
                std::to_string(m.channels[i].offset) + "]";
      line += "]";
    } else if (m.type == MessageType::Frame) {
      const Frame& f = m.frame;
      line += ",\"index\":" + std::to_string(f.index) + ",\"pts\":" + N(f.pts) + ",\"root\":" + V(f.root);
      line += ",\"rotations\":" + Qs(f.rotations, [](const Quat& q) { return q; });
      line += ",\"unity_root\":" + V(ToUnityPosition(f.root, skeleton.unit_to_m));
      line += ",\"unity_rotations\":" + Qs(f.rotations, ToUnityRotation);
      line += ",\"unreal_root\":" + V(ToUnrealPosition(f.root, skeleton.unit_to_m * 100.0));
      line += ",\"unreal_rotations\":" + Qs(f.rotations, ToUnrealRotation);
      if (!skeleton.joints.empty())
        line += ",\"global_rotations\":" + Qs(GlobalRotations(skeleton, f.rotations), [](const Quat& q) { return q; });
      if (!f.channels.empty()) {
        std::string cs;
        for (const auto& kv : f.channels) {
          cs += std::string(cs.empty() ? "" : ",") + "\"" + Escape(kv.first) + "\":[";
          for (size_t i = 0; i < kv.second.size(); ++i) cs += (i ? "," : "") + N(kv.second[i]);
          cs += "]";
        }
        line += ",\"channels\":{" + cs + "}";
      }
      if (!f.face.empty()) {
        std::string fs;
        for (const auto& kv : f.face) fs += std::string(fs.empty() ? "" : ",") + "\"" + Escape(kv.first) + "\":" + N(kv.second);
        line += ",\"face\":{" + fs + "}";
      }
    } else if (m.type == MessageType::Status) {
      line += ",\"latency_ms\":" + N(m.status.latency_ms) + ",\"dropped\":" + std::to_string(m.status.dropped);
    } else if (m.type == MessageType::End) {
      line += ",\"frames\":" + std::to_string(m.end_frames);
    }
    std::printf("%s}\n", line.c_str());
  }
  return 0;
}
