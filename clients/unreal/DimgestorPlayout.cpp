// Playout buffer; see DimgestorPlayout.h.
#include "DimgestorPlayout.h"

#include <cmath>

namespace dimgestor {

namespace {
constexpr size_t kMaxQueue = 256;
constexpr double kLateMarginS = 0.02;
}  // namespace

void FramePlayout::Reset() {
  queue_.clear();
  has_offset = false;
}

void FramePlayout::Push(const Frame& frame, double now) {
  const Frame* last = queue_.empty() ? nullptr : &queue_.back();
  if (!has_offset || (last && (frame.index < last->index || frame.pts <= last->pts))) {
    queue_.clear();  // a new stream (own audio session, --loop, reconnect)
    offset = now - frame.pts + delay_s;
    has_offset = true;
  } else if (now - offset > frame.pts) {
    offset = now - frame.pts + kLateMarginS;  // late: show it now, and keep that much more buffer
    ++reanchors;
  } else if (frame.pts - (now - offset) > 2 * delay_s) {
    offset = now - frame.pts + delay_s;  // too much buffered: catch up
    ++reanchors;
  }
  queue_.push_back(frame);
  if (queue_.size() > kMaxQueue) queue_.pop_front();
}

bool FramePlayout::Sample(double now, Frame& out) {
  if (queue_.empty()) return false;
  const double t = now - offset;
  while (queue_.size() > 1 && queue_[1].pts <= t) queue_.pop_front();  // keep the last frame at or before t
  const Frame& a = queue_[0];
  if (queue_.size() == 1 || t <= a.pts || queue_[1].rotations.size() != a.rotations.size()) { out = a; return true; }
  const Frame& b = queue_[1];
  const double u = (t - a.pts) / (b.pts - a.pts);
  out.index = a.index;
  out.pts = t;
  out.root = Vec3{a.root.x + (b.root.x - a.root.x) * u, a.root.y + (b.root.y - a.root.y) * u,
                  a.root.z + (b.root.z - a.root.z) * u};
  out.rotations.resize(a.rotations.size());
  for (size_t j = 0; j < a.rotations.size(); ++j)
    out.rotations[j] = Slerp(a.rotations[j], b.rotations[j], u);
  out.face = LerpFace(a.face, b.face, u);
  return true;
}

std::map<std::string, double> LerpFace(const std::map<std::string, double>& a, const std::map<std::string, double>& b,
                                       double u) {
  std::map<std::string, double> r;
  for (const auto& kv : a) {
    auto it = b.find(kv.first);
    r[kv.first] = it == b.end() ? kv.second : kv.second + (it->second - kv.second) * u;
  }
  return r;
}

Quat Slerp(const Quat& a, const Quat& b, double u) {
  double dot = a.w * b.w + a.x * b.x + a.y * b.y + a.z * b.z;
  const double s = dot < 0 ? -1 : 1;  // q and -q are the same rotation: take the nearer one
  dot *= s;
  double wa, wb;
  if (dot > 0.9995) {  // nearly equal: linear is exact enough and avoids 0/0
    wa = 1 - u;
    wb = u;
  } else {
    const double th = std::acos(dot), sn = std::sin(th);
    wa = std::sin((1 - u) * th) / sn;
    wb = std::sin(u * th) / sn;
  }
  Quat r{wa * a.w + wb * s * b.w, wa * a.x + wb * s * b.x, wa * a.y + wb * s * b.y, wa * a.z + wb * s * b.z};
  const double n = std::sqrt(r.w * r.w + r.x * r.x + r.y * r.y + r.z * r.z);
  return Quat{r.w / n, r.x / n, r.y / n, r.z / n};
}

}  // namespace dimgestor
