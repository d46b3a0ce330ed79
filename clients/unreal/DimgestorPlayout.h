// Playout buffer: the server computes motion window by window, so frames arrive in bursts (e.g. 4 frames
// every 200 ms). Applying each on arrival would animate at 5 fps; instead every frame is shown at its own
// presentation time, pts + offset on the local clock, interpolating between neighbours (root: linear,
// rotations: slerp, face weights: linear, so the mouth moves with the body). The same rules are in
// clients/web/playout.js and clients/unity/DimgestorPlayout.cs.
//
// offset is set when a stream starts (first frame shown delay_s after it arrived), grows when a frame
// arrives too late to be shown on time, and shrinks when more than 2 x delay_s is buffered. Standard
// library only; the caller passes the clock, so it is deterministic and testable.
#pragma once

#include <deque>
#include <map>
#include <string>

#include "DimgestorProtocol.h"

namespace dimgestor {

class FramePlayout {
 public:
  explicit FramePlayout(double delay = 0.3) : delay_s(delay) {}

  double delay_s;           // buffer kept when a stream starts
  bool has_offset = false;  // false until a stream starts
  double offset = 0;        // local seconds minus pts
  int reanchors = 0;        // times the clock was moved because frames came late or piled up

  // Forget everything: the next frame starts a new playout clock.
  void Reset();
  // Add a frame that arrived at local time `now` (seconds).
  void Push(const Frame& frame, double now);
  // The pose to show at local time `now`, interpolated; false before any frame.
  bool Sample(double now, Frame& out);
  size_t size() const { return queue_.size(); }

 private:
  std::deque<Frame> queue_;
};

// Spherical interpolation of unit quaternions along the shorter arc.
Quat Slerp(const Quat& a, const Quat& b, double u);

// Face weights between two frames; a name the later frame lacks (another set) keeps a's weight.
std::map<std::string, double> LerpFace(const std::map<std::string, double>& a, const std::map<std::string, double>& b,
                                       double u);

}  // namespace dimgestor
