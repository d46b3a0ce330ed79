// Test driver: UDimgestorComponent (on engine stand-ins) as a talker whose server says slow_down and later
// resume (protocol revision 2), through its WebSocket events. Chunk k is k-valued samples (0.4 s at 1 kHz) so
// the log of what went out (IWebSocket stub: text:JSON | binary:FIRST_SAMPLE:BYTES) names each chunk.
// Prints one JSON object; tests/test_clients_unreal.py checks it.
#include <cstdio>
#include <string>

#include "../DimgestorComponent.h"
#include "Components/PoseableMeshComponent.h"
#include "WebSocketsModule.h"
#include "check_util.h"


int main() {
  UPoseableMeshComponent mesh;
  OneBoneMesh(mesh);
  UDimgestorComponent component;
  component.TargetMesh = &mesh;
  component.MaxHeldAudioS = 1.f;
  component.Speaker = TEXT("scott");  // (revision 9: in its hello)
  component.BeginPlay();
  TSharedPtr<IWebSocket> socket = FWebSocketsModule::Get().StubLast;
  socket->StubConnected = true;
  socket->OnConnected().StubBroadcast();
  const size_t before = socket->StubSent.size();  // (our hello)

  auto send = [&](int k) {
    TArray<float> chunk;
    for (int i = 0; i < 400; ++i) chunk.Add(float(k));
    return component.SendAudio(chunk, 1000, 1);
  };
  bool ok = send(1);
  socket->OnMessage().StubBroadcast(Wide(R"({"type": "error", "code": "slow_down", "message": "audio arrives faster"})"));
  const bool paused = component.bAudioPaused;
  const std::string notice = Narrow(component.AudioNotice);
  ok = send(2) && send(3) && ok;
  socket->OnMessage().StubBroadcast(Wide(R"({"type": "future_thing", "x": [1]})"));
  ok = send(4) && send(5) && send(6) && ok;  // 2 s held, 1 s allowed: 2, 3 and 4 dropped
  component.EndAudio();                       // waits for resume
  const size_t while_paused = socket->StubSent.size();
  socket->OnMessage().StubBroadcast(Wide(R"({"type": "resume", "backlog_s": 14.9})"));
  std::string log;
  for (size_t i = before; i < socket->StubSent.size(); ++i) log += (log.empty() ? "" : ",") + Quoted(socket->StubSent[i]);
  std::printf("{\"ok\":%s,\"paused\":%s,\"paused_after\":%s,\"notice\":%s,\"sent_while_paused\":%zu,\"dropped_s\":%.9g,"
              "\"last_error\":%s,\"log\":[%s]}\n", ok ? "true" : "false", paused ? "true" : "false",
              component.bAudioPaused ? "true" : "false", Quoted(notice).c_str(), while_paused - before,
              double(component.DroppedAudioS), Quoted(Narrow(component.LastError)).c_str(), log.c_str());
  return 0;
}
