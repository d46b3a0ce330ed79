// Test driver: runs UDimgestorComponent (built against tests/stubs) through its public life cycle on frames
// recorded from a live server: BeginPlay captures the rest pose of a stand-in Mannequin-named mesh whose
// bones have other axes than the server skeleton (a random rotation per bone, plus an extra "root" bone);
// the server's messages are fired through the WebSocket events (binary ones in two fragments) on a
// real-time clock, and TickComponent poses the mesh one playout delay after each frame arrived. Prints the
// mesh's reference pose, then per frame each bound bone's component-space location (cm);
// tests/test_clients_unreal.py compares them with the server skeleton's forward kinematics. The mesh's
// reference pose is the skeleton's rest (a T-pose), or with "apose" an A-pose: each arm (upper arm and below)
// turned 45 degrees down at the upper arm's joint.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <map>
#include <random>
#include <string>
#include <vector>

#include "../DimgestorComponent.h"
#include "WebSocketsModule.h"
#include "Components/PoseableMeshComponent.h"

namespace fs = std::filesystem;
using namespace dimgestor;

static FString Wide(const std::string& s) { std::wstring w(s.begin(), s.end()); return FString(w.c_str()); }

int main(int argc, char** argv) {
  if (argc < 3 || argc > 4 || (argc == 4 && std::string(argv[3]) != "apose")) {
    std::fprintf(stderr, "usage: retarget_check FOLDER YAW_DEGREES [apose]\n");
    return 2;
  }
  std::vector<fs::path> files;
  for (const auto& e : fs::directory_iterator(argv[1])) files.push_back(e.path());
  std::sort(files.begin(), files.end());
  std::vector<std::pair<fs::path, std::string>> messages;
  Hello hello;
  for (const fs::path& p : files) {
    std::ifstream in(p, std::ios::binary);
    std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    messages.emplace_back(p, bytes);
    Message m;
    std::string error;
    if (p.extension() == ".json" && ParseMessage(bytes, m, error) && m.type == MessageType::Hello) hello = m.hello;
  }
  const Skeleton& sk = hello.skeleton;
  const double unit_to_cm = sk.unit_to_m * 100.0;

  UDimgestorComponent component;
  component.SourceToComponent = FRotator(0.0, std::atof(argv[2]), 0.0);
  const FQuat C = component.SourceToComponent.Quaternion();

  // Rest pose of the server skeleton, then the stand-in mesh: "root" plus one bone per mapped joint.
  std::vector<Quat> rest_global = GlobalRotations(sk, sk.rest_rotations);
  std::vector<Vec3> rest_pos(sk.joints.size());
  for (size_t j = 0; j < sk.joints.size(); ++j) {
    if (sk.parents[j] < 0) { rest_pos[j] = sk.offsets[j]; continue; }
    Quat g = rest_global[size_t(sk.parents[j])];
    Quat v = g * Quat{0, sk.offsets[j].x, sk.offsets[j].y, sk.offsets[j].z} * Conjugate(g);
    const Vec3& p = rest_pos[size_t(sk.parents[j])];
    rest_pos[j] = Vec3{p.x + v.x, p.y + v.y, p.z + v.z};
  }
  UPoseableMeshComponent mesh;
  mesh.StubNames.push_back(FName(TEXT("root")));
  mesh.StubParents.push_back(-1);
  mesh.StubLocal.emplace_back();
  std::map<int, int32> bone_of_joint;
  std::map<int32, std::string> humanoid_of_bone;
  std::vector<std::pair<int, std::string>> mapped;
  for (const auto& kv : hello.humanoid)
    if (sk.IndexOf(kv.second) >= 0 && component.HumanoidToBone.Find(Wide(kv.first))) mapped.emplace_back(sk.IndexOf(kv.second), kv.first);
  std::sort(mapped.begin(), mapped.end());
  std::mt19937 rng(11);
  std::normal_distribution<double> normal;
  for (const auto& jm : mapped) {
    int p = sk.parents[size_t(jm.first)];
    while (p >= 0 && !bone_of_joint.count(p)) p = sk.parents[size_t(p)];
    const int32 index = int32(mesh.StubNames.size());
    mesh.StubNames.push_back(*component.HumanoidToBone.Find(Wide(jm.second)));
    mesh.StubParents.push_back(p >= 0 ? bone_of_joint[p] : 0);
    mesh.StubLocal.emplace_back();
    Vec3 u = ToUnrealPosition(rest_pos[size_t(jm.first)], unit_to_cm);
    FQuat axes = FQuat(normal(rng), normal(rng), normal(rng), normal(rng)).GetNormalized();
    mesh.SetBoneTransformByName(mesh.StubNames.back(), FTransform(C * axes, C.RotateVector(FVector(u.x, u.y, u.z))),
                                EBoneSpaces::ComponentSpace);
    bone_of_joint[jm.first] = index;
    humanoid_of_bone[index] = jm.second;
  }
  if (argc == 4) {  // A-pose: each upper arm turned 45 degrees about the axis that lowers it (children follow)
    for (const char* side : {"Left", "Right"}) {
      const FName upper = *component.HumanoidToBone.Find(Wide(std::string(side) + "UpperArm"));
      const FName lower = *component.HumanoidToBone.Find(Wide(std::string(side) + "LowerArm"));
      FTransform t = mesh.GetBoneTransformByName(upper, EBoneSpaces::ComponentSpace);
      const FVector d = mesh.GetBoneTransformByName(lower, EBoneSpaces::ComponentSpace).GetLocation() - t.GetLocation();
      FVector axis(-d.Y, d.X, 0.0);  // d x (0, 0, -1): turns d towards -Z (down)
      const double half = 3.14159265358979323846 / 8, s = std::sin(half) / std::sqrt(axis.SizeSquared());
      t.SetRotation(FQuat(axis.X * s, axis.Y * s, 0.0, std::cos(half)) * t.GetRotation());
      mesh.SetBoneTransformByName(upper, t, EBoneSpaces::ComponentSpace);
    }
  }

  auto print_bones = [&](const char* key) {  // {"KEY": {humanoid name: component-space location}}
    std::string line = std::string("{\"") + key + "\":{";
    bool first = true;
    for (const auto& bh : humanoid_of_bone) {
      FVector t = mesh.GetBoneTransformByName(mesh.StubNames[size_t(bh.first)], EBoneSpaces::ComponentSpace).GetLocation();
      char buf[160];
      std::snprintf(buf, sizeof buf, "%s\"%s\":[%.9g,%.9g,%.9g]", first ? "" : ",", bh.second.c_str(), t.X, t.Y, t.Z);
      line += buf;
      first = false;
    }
    std::printf("%s}}\n", line.c_str());
  };
  print_bones("reference");

  component.TargetMesh = &mesh;
  component.BeginPlay();
  TSharedPtr<IWebSocket> socket = FWebSocketsModule::Get().StubLast;
  socket->StubConnected = true;
  socket->OnConnected().StubBroadcast();

  // A real-time timeline: each frame arrives at its pts and is looked at one playout delay later, when
  // the component must show exactly that frame (the same delay rule as the component's).
  const double delay = (hello.window_ms > 0 ? hello.window_ms / 1000.0 : 0.25) + 0.06;
  struct Event { double time; int kind; size_t message; };  // kind 0: arrival, 1: tick
  std::vector<Event> events;
  for (size_t i = 0; i < messages.size(); ++i) {
    const std::string& bytes = messages[i].second;
    Message m;
    std::string error;
    bool ok = messages[i].first.extension() == ".bin"
                  ? DecodeBinaryFrame(reinterpret_cast<const uint8_t*>(bytes.data()), bytes.size(), m.frame, error)
                  : (ParseMessage(bytes, m, error) && m.type == MessageType::Frame);
    if (!ok) { events.push_back({-1.0, 0, i}); continue; }  // hello, status...: before any frame
    events.push_back({m.frame.pts, 0, i});
    events.push_back({m.frame.pts + delay, 1, i});
  }
  std::stable_sort(events.begin(), events.end(), [](const Event& a, const Event& b) {
    return a.time < b.time || (a.time == b.time && a.kind < b.kind);
  });
  for (const Event& e : events) {
    FPlatformTime::StubNow() = e.time;
    const std::string& bytes = messages[e.message].second;
    if (e.kind == 0) {
      if (messages[e.message].first.extension() == ".bin") {  // two fragments: the component must join them
        const size_t half = bytes.size() / 2;
        socket->OnBinaryMessage().StubBroadcast(bytes.data(), half, false);
        socket->OnBinaryMessage().StubBroadcast(bytes.data() + half, bytes.size() - half, true);
      } else {
        socket->OnMessage().StubBroadcast(Wide(bytes));
      }
      continue;
    }
    component.TickComponent(1.f / 60.f, LEVELTICK_All, nullptr);
    print_bones("bones");
  }
  std::fprintf(stderr, "frames received %lld, sent %zu text message(s)\n", (long long)component.FramesReceived,
               socket->StubSentText.size());
  return component.FramesReceived > 0 ? 0 : 1;
}
