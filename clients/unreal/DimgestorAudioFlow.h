// Flow control of the audio a client sends (protocol v1 revision 2, docs/protocol.md "Audio"), in
// engine-independent C++17 (standard library only, no exceptions), tested outside the engine
// (clients/unreal/tests/flow_check.cpp).
//
// Between a `slow_down` error (a notice: the server has 30 s of our audio queued) and its `resume`, the server
// wants no more audio. Chunks offered meanwhile are held, in order, at most max_held_s seconds of them: a live
// microphone wants now, not what was said long ago, so beyond the bound the oldest are dropped and counted
// (dropped_s). At `resume` the held chunks go out first; an audio_end asked for while paused goes after them.
#pragma once

#include <cstdint>
#include <deque>
#include <utility>
#include <vector>

namespace dimgestor {

constexpr double kDefaultMaxHeldS = 10.0;

class AudioFlow {
 public:
  using Chunk = std::vector<uint8_t>;

  explicit AudioFlow(double max_held = kDefaultMaxHeldS) : max_held_s(max_held) {}

  // A chunk of `seconds` of audio to send: the chunks that may go now, in order (none while paused).
  std::vector<Chunk> Offer(Chunk chunk, double seconds);
  // The server said `slow_down`: hold what comes until `resume`.
  void SlowDown();
  // The server said `resume`: the held chunks, to send now (then audio_end if TakeEndPending()).
  std::vector<Chunk> Resume();
  // No more audio: true if audio_end may go now; false if paused (it goes after Resume's chunks).
  bool End();
  // Whether an audio_end was waiting for `resume`; clears it.
  bool TakeEndPending();
  // The held chunks are discarded, counted as dropped (their audio format is being replaced).
  void DropHeld();
  // A new connection: nothing paused or held (what was held belonged to the old session).
  void Reset();

  bool paused() const { return paused_; }
  double held_s() const { return held_s_; }
  double dropped_s() const { return dropped_s_; }
  int64_t dropped_chunks() const { return dropped_chunks_; }
  int64_t pauses() const { return pauses_; }
  int64_t resumes() const { return resumes_; }

  double max_held_s;

 private:
  std::vector<Chunk> TakeHeld();

  std::deque<std::pair<Chunk, double>> held_;  // (chunk, seconds), oldest first
  double held_s_ = 0, dropped_s_ = 0;
  int64_t dropped_chunks_ = 0, pauses_ = 0, resumes_ = 0;
  bool paused_ = false, end_pending_ = false;
};

}  // namespace dimgestor
