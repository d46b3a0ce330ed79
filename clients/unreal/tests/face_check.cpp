// Test driver: the face (protocol revision 7) through UDimgestorComponent on the engine stand-ins. The recorded server
// messages in FOLDER (NNNNNN.json / .bin) are fired through its WebSocket events (binary frames in two fragments),
// each frame at its pts on the stand-in clock; then at each of SPEC's times the component ticks one playout delay
// later and shows the frame due (interpolated), setting FaceMesh's morph targets and FaceCurves (and prints what the
// component says: bFaceWithheld, FaceNotice, LastError). SPEC is JSON:
// {"face_names": "arkit", "map": [[face, target], ...], "metahuman": bool, "face_mesh": bool, "times": [pts, ...],
// "curves_to_read": [...]}. A file NNNNNN*.tick in FOLDER ticks the component there, between the messages, one playout
// delay after the newest frame's pts (the frame due is shown then). Prints the hello
// the component sent, then one JSON line per time; tests/test_clients_unreal.py checks them.
#include <algorithm>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <new>
#include <string>
#include <vector>

#include "../DimgestorComponent.h"
#include "../DimgestorJson.h"
#include "Components/PoseableMeshComponent.h"
#include "Components/SkeletalMeshComponent.h"
#include "WebSocketsModule.h"
#include "check_util.h"

namespace fs = std::filesystem;
using namespace dimgestor;

static std::string Read(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  return std::string((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
}

static std::string Weights(const std::vector<std::pair<FName, float>>& w) {
  std::string o = "{";
  for (size_t i = 0; i < w.size(); ++i) {
    char b[48];
    std::snprintf(b, sizeof b, ":%.9g", double(w[i].second));
    o += (i ? "," : "") + Quoted(Narrow(w[i].first.ToString())) + b;
  }
  return o + "}";
}

int main(int argc, char** argv) {
  if (argc != 3) { std::fprintf(stderr, "usage: face_check FOLDER SPEC\n"); return 2; }
  JsonValue spec;
  std::string error;
  if (!ParseJson(Read(argv[2]), spec, error)) { std::fprintf(stderr, "spec: %s\n", error.c_str()); return 2; }

  UPoseableMeshComponent body;
  OneBoneMesh(body);
  USkeletalMeshComponent face;
  // Made on garbage, as a member the component leaves uninitialised would be (the engine zeroes a UObject's
  // memory, the stand-ins do not): whatever it reads must be set by itself or by us.
  alignas(UDimgestorComponent) static unsigned char storage[sizeof(UDimgestorComponent)];
  std::memset(storage, 0xA5, sizeof storage);
  UDimgestorComponent& component = *new (storage) UDimgestorComponent;
  component.TargetMesh = &body;
  if (spec.Get("face_mesh")->b) component.FaceMesh = &face;  // else left as it is: curves only
  component.FaceNames = Wide(spec.Get("face_names")->s);
  component.bMetaHumanCurveNames = spec.Get("metahuman")->b;
  for (const JsonValue& e : spec.Get("map")->items) component.FaceNameMap.Add(Wide(e.items[0].s), FName(*Wide(e.items[1].s)));
  component.BeginPlay();
  TSharedPtr<IWebSocket> socket = FWebSocketsModule::Get().StubLast;
  socket->StubConnected = true;
  socket->OnConnected().StubBroadcast();
  std::printf("{\"hello\":%s}\n", Quoted(Narrow(socket->StubSentText.at(0))).c_str());

  const double delay = 0.25 + 0.06;  // the component's playout delay for a hello without window_ms
  std::vector<fs::path> files;
  for (const auto& e : fs::directory_iterator(argv[1])) files.push_back(e.path());
  std::sort(files.begin(), files.end());
  double newest = 0;
  for (const fs::path& p : files) {
    const std::string bytes = Read(p);
    if (p.extension() == ".tick") {
      FPlatformTime::StubNow() = newest + delay;
      component.TickComponent(1.f / 60.f, LEVELTICK_All, nullptr);
      continue;
    }
    if (p.extension() == ".bin") {
      Frame f;  // (its pts: the time it arrives, on time)
      if (DecodeBinaryFrame(reinterpret_cast<const uint8_t*>(bytes.data()), bytes.size(), f, error)) FPlatformTime::StubNow() = newest = f.pts;
      const size_t half = bytes.size() / 2;
      socket->OnBinaryMessage().StubBroadcast(bytes.data(), half, false);
      socket->OnBinaryMessage().StubBroadcast(bytes.data() + half, bytes.size() - half, true);
    } else {
      Message m;
      if (ParseMessage(bytes, m, error) && m.type == MessageType::Frame) FPlatformTime::StubNow() = newest = m.frame.pts;
      socket->OnMessage().StubBroadcast(Wide(bytes));
    }
  }
  for (const JsonValue& t : spec.Get("times")->items) {
    FPlatformTime::StubNow() = t.n + delay;
    component.TickComponent(1.f / 60.f, LEVELTICK_All, nullptr);
    std::vector<std::pair<FName, float>> morphs(face.StubMorphs.begin(), face.StubMorphs.end()), curves;
    for (const auto& name : spec.Get("curves_to_read")->items) {
      const FName curve(*Wide(name.s));
      curves.emplace_back(curve, component.GetFaceCurve(curve));
    }
    std::printf("{\"t\":%.17g,\"morphs\":%s,\"curves\":%s,\"curve_count\":%d,\"frames\":%lld,\"withheld\":%s,"
                "\"face_notice\":%s,\"last_error\":%s}\n", t.n, Weights(morphs).c_str(), Weights(curves).c_str(),
                int(component.FaceCurves.Num()), (long long)component.FramesReceived,
                component.bFaceWithheld ? "true" : "false", Quoted(Narrow(component.FaceNotice)).c_str(),
                Quoted(Narrow(component.LastError)).c_str());
  }
  return 0;
}
