#include "DimgestorAudioFlow.h"

namespace dimgestor {

std::vector<AudioFlow::Chunk> AudioFlow::Offer(Chunk chunk, double seconds) {
  held_.emplace_back(std::move(chunk), seconds);
  held_s_ += seconds;
  while (held_s_ > max_held_s && held_.size() > 1) {
    held_s_ -= held_.front().second;
    dropped_s_ += held_.front().second;
    ++dropped_chunks_;
    held_.pop_front();
  }
  return paused_ ? std::vector<Chunk>() : TakeHeld();
}

void AudioFlow::SlowDown() {
  if (!paused_) ++pauses_;
  paused_ = true;
}

std::vector<AudioFlow::Chunk> AudioFlow::Resume() {
  if (paused_) ++resumes_;
  paused_ = false;
  return TakeHeld();
}

bool AudioFlow::End() {
  end_pending_ = paused_;
  return !paused_;
}

bool AudioFlow::TakeEndPending() {
  const bool e = end_pending_;
  end_pending_ = false;
  return e;
}

void AudioFlow::DropHeld() {
  for (const auto& c : held_) {
    dropped_s_ += c.second;
    ++dropped_chunks_;
  }
  held_.clear();
  held_s_ = 0;
}

void AudioFlow::Reset() {
  paused_ = end_pending_ = false;
  held_.clear();
  held_s_ = 0;
}

std::vector<AudioFlow::Chunk> AudioFlow::TakeHeld() {
  std::vector<Chunk> out;
  out.reserve(held_.size());
  for (auto& c : held_) out.push_back(std::move(c.first));
  held_.clear();
  held_s_ = 0;
  return out;
}

}  // namespace dimgestor
