// Test driver: UDimgestorComponent (on engine stand-ins) talking when its worker stops (protocol revision 3): the
// server says goaway with a token; the socket closes (1012); the component connects again at once, declares its
// audio format, sends resume_session, holds what SendAudio gets meanwhile, and at session_resumed re-sends its
// audio from the sample the saved state covers, then what it held. Chunk k is k-valued samples (0.4 s at 1 kHz),
// so the log of what went out (IWebSocket stub: text:JSON | binary:FIRST_SAMPLE:BYTES) names each chunk.
// Prints one JSON object; tests/test_clients_unreal.py checks it.
#include <cstdio>
#include <string>

#include "../DimgestorComponent.h"
#include "Components/PoseableMeshComponent.h"
#include "WebSocketsModule.h"
#include "check_util.h"

static std::string Log(const TSharedPtr<IWebSocket>& socket, size_t from) {
  std::string log;
  for (size_t i = from; i < socket->StubSent.size(); ++i) log += (log.empty() ? "" : ",") + Quoted(socket->StubSent[i]);
  return log;
}

int main() {
  UPoseableMeshComponent mesh;
  OneBoneMesh(mesh);
  UDimgestorComponent component;
  component.TargetMesh = &mesh;
  component.BeginPlay();
  TSharedPtr<IWebSocket> first = FWebSocketsModule::Get().StubLast;
  first->StubConnected = true;
  first->OnConnected().StubBroadcast();
  const size_t before = first->StubSent.size();  // (our hello)

  auto send = [&](int k) {
    TArray<float> chunk;
    for (int i = 0; i < 400; ++i) chunk.Add(float(k));
    return component.SendAudio(chunk, 1000, 1);
  };
  bool ok = send(1) && send(2);
  // The worker stops: its saved state covers chunk 1 only (sample 400); chunk 2 was ignored while it was saved.
  first->OnMessage().StubBroadcast(Wide(R"({"type": "goaway", "reason": "restart", "resume_token": "k3J-x_9", "samples": 400, "rate": 1000, "frames": 7})"));
  ok = send(3) && ok;  // held
  first->StubConnected = false;
  first->OnClosed().StubBroadcast(1012, Wide("restart: resume_session with the goaway's token"), true);
  const std::string moving = Narrow(component.ConnectionState);
  component.TickComponent(0.1f, LEVELTICK_All, nullptr);  // reconnects at once
  TSharedPtr<IWebSocket> second = FWebSocketsModule::Get().StubLast;
  const bool reconnected = second != first;
  second->StubConnected = true;
  second->OnConnected().StubBroadcast();
  ok = send(4) && ok;  // still held: not resumed yet
  const size_t before_resumed = second->StubSent.size();
  second->OnMessage().StubBroadcast(Wide(R"({"type": "session_resumed", "samples": 400, "rate": 1000, "frames": 7})"));
  ok = send(5) && ok;
  component.EndAudio();
  std::printf("{\"ok\":%s,\"moving\":%s,\"reconnected\":%s,\"handovers\":%d,\"resumed\":%d,\"paused_after\":%s,"
              "\"held_until_resumed\":%zu,\"last_error\":%s,\"first\":[%s],\"second\":[%s]}\n",
              ok ? "true" : "false", Quoted(moving).c_str(), reconnected ? "true" : "false", int(component.Handovers),
              int(component.Resumed), component.bAudioPaused ? "true" : "false", before_resumed,
              Quoted(Narrow(component.LastError)).c_str(), Log(first, before).c_str(), Log(second, 0).c_str());
  return 0;
}
