// dimgestor protocol v1 decoding; see DimgestorProtocol.h. Standard library only, no exceptions.
#include "DimgestorProtocol.h"

#include <algorithm>
#include <cctype>
#include <cstdio>
#include <cstring>

#include "DimgestorJson.h"

namespace dimgestor {

namespace {

// ------------------------------------------------------------------ typed access

struct Fields {
  std::string& error;
  bool Num(const JsonValue& o, const char* key, double dflt, double& out) {
    const JsonValue* v = o.Get(key);
    if (!v || v->kind == JsonValue::Null) { out = dflt; return true; }
    if (v->kind != JsonValue::Number) { error = std::string("\"") + key + "\" is not a number"; return false; }
    out = v->n;
    return true;
  }
  bool Str(const JsonValue& o, const char* key, const char* dflt, std::string& out) {
    const JsonValue* v = o.Get(key);
    if (!v || v->kind == JsonValue::Null) { out = dflt; return true; }
    if (v->kind != JsonValue::String) { error = std::string("\"") + key + "\" is not a string"; return false; }
    out = v->s;
    return true;
  }
  const JsonValue* Kind(const JsonValue& o, const char* key, JsonValue::Kind kind, const char* what) {
    const JsonValue* v = o.Get(key);
    if (!v || v->kind != kind) { error = std::string("\"") + key + "\" is missing or not " + what; return nullptr; }
    return v;
  }
  bool Numbers(const JsonValue& v, size_t n, double* out, const std::string& what) {
    if (v.kind != JsonValue::Array || v.items.size() != n) {
      error = what + (n == 3 ? " is not [x, y, z]" : " is not [w, x, y, z]");
      return false;
    }
    for (size_t i = 0; i < n; ++i) {
      if (v.items[i].kind != JsonValue::Number) { error = what + " has a non-number"; return false; }
      out[i] = v.items[i].n;
    }
    return true;
  }
  bool ToVec(const JsonValue& v, Vec3& out, const std::string& what) {
    double a[3];
    if (!Numbers(v, 3, a, what)) return false;
    out = Vec3{a[0], a[1], a[2]};
    return true;
  }
  bool ToQuat(const JsonValue& v, Quat& out, const std::string& what) {
    double a[4];
    if (!Numbers(v, 4, a, what)) return false;
    out = Quat{a[0], a[1], a[2], a[3]};
    return true;
  }
};

void Strings(const JsonValue* l, std::vector<std::string>& out) {
  if (l && l->kind == JsonValue::Array)
    for (const JsonValue& x : l->items) out.push_back(x.kind == JsonValue::String ? x.s : "");
}

// A binary layout (hello.channels or a `channels` message): each channel's name, size, byte offset, labels.
bool ParseChannels(const JsonValue& cs, const std::string& where, std::vector<ChannelSpec>& out, std::string& error) {
  Fields f{error};
  if (cs.kind != JsonValue::Array) { error = where + " is not an array"; return false; }
  out.clear();
  for (size_t i = 0; i < cs.items.size(); ++i) {
    const JsonValue& c = cs.items[i];
    std::string at = where + "[" + std::to_string(i) + "]";
    ChannelSpec spec;
    double size, offset;
    if (c.kind != JsonValue::Object) { error = at + " is not an object"; return false; }
    if (!f.Str(c, "name", "", spec.name) || !f.Num(c, "size", 0, size) || !f.Num(c, "offset", 0, offset)) return false;
    if (size < 0 || offset < 0 || size > 1e6 || offset > 1e9) { error = at + ": bad size or offset"; return false; }
    spec.size = size_t(size);
    spec.offset = size_t(offset);
    Strings(c.Get("labels"), spec.labels);
    out.push_back(spec);
  }
  return true;
}

bool ParseHello(const JsonValue& o, Hello& h, std::string& error) {
  Fields f{error};
  double protocol, fps, lookahead;
  if (!f.Num(o, "protocol", 0, protocol) || !f.Str(o, "server", "", h.server) || !f.Num(o, "fps", 0, fps) ||
      !f.Str(o, "encoding", "json", h.encoding) || !f.Num(o, "lookahead_s", 0, lookahead) ||
      !f.Num(o, "window_ms", 0, h.window_ms))
    return false;
  h.protocol = int(protocol);
  h.fps = fps;
  h.lookahead_s = lookahead;
  if (h.protocol != kProtocolVersion) {
    error = "server speaks protocol " + std::to_string(h.protocol) + ", this client " + std::to_string(kProtocolVersion);
    return false;
  }
  const JsonValue* sk = f.Kind(o, "skeleton", JsonValue::Object, "an object");
  if (!sk) return false;
  const JsonValue* joints = f.Kind(*sk, "joints", JsonValue::Array, "an array");
  const JsonValue* parents = joints ? f.Kind(*sk, "parents", JsonValue::Array, "an array") : nullptr;
  const JsonValue* offsets = parents ? f.Kind(*sk, "offsets", JsonValue::Array, "an array") : nullptr;
  if (!offsets) return false;
  const JsonValue* rest = sk->Get("rest_rotations");
  size_t n = joints->items.size();
  if (parents->items.size() != n || offsets->items.size() != n ||
      (rest && (rest->kind != JsonValue::Array || rest->items.size() != n))) {
    error = "hello.skeleton: " + std::to_string(n) + " joints but " + std::to_string(parents->items.size()) +
            " parents, " + std::to_string(offsets->items.size()) + " offsets" + (rest ? " or bad rest_rotations" : "");
    return false;
  }
  Skeleton& s = h.skeleton;
  s.joints.resize(n); s.parents.resize(n); s.offsets.resize(n); s.rest_rotations.assign(n, Quat{});
  for (size_t j = 0; j < n; ++j) {
    std::string at = "[" + std::to_string(j) + "]";
    if (joints->items[j].kind != JsonValue::String) { error = "hello.skeleton.joints" + at + " is not a string"; return false; }
    s.joints[j] = joints->items[j].s;
    const JsonValue& p = parents->items[j];
    if (p.kind != JsonValue::Number || p.n < -1 || p.n >= double(j)) {
      error = "hello.skeleton.parents" + at + ": parents must be -1 or an earlier joint";
      return false;
    }
    s.parents[j] = int(p.n);
    if (!f.ToVec(offsets->items[j], s.offsets[j], "hello.skeleton.offsets" + at)) return false;
    if (rest && !f.ToQuat(rest->items[j], s.rest_rotations[j], "hello.skeleton.rest_rotations" + at)) return false;
  }
  if (!f.Str(*sk, "units", "cm", s.units)) return false;
  s.unit_to_m = s.units == "m" ? 1.0 : s.units == "mm" ? 0.001 : 0.01;
  if (const JsonValue* hm = o.Get("humanoid")) {
    if (hm->kind == JsonValue::Object)
      for (size_t i = 0; i < hm->keys.size(); ++i)
        if (hm->items[i].kind == JsonValue::String) h.humanoid[hm->keys[i]] = hm->items[i].s;
  }
  if (const JsonValue* a = o.Get("audio")) {
    if (a->kind == JsonValue::Object) {
      const JsonValue* acc = a->Get("accepts");
      h.audio_accepts = acc && acc->kind == JsonValue::Bool && acc->b;
      double rate;
      if (!f.Num(*a, "rate", 16000, rate)) return false;
      h.audio_rate = int(rate);
      if (const JsonValue* fm = a->Get("formats"))
        if (fm->kind == JsonValue::Array)
          for (const JsonValue& x : fm->items)
            if (x.kind == JsonValue::String) h.audio_formats.push_back(x.s);
    }
  }
  if (const JsonValue* cs = o.Get("channels"))
    if (!ParseChannels(*cs, "hello.channels", h.channels, error)) return false;
  if (const JsonValue* fo = o.Get("face")) {
    if (fo->kind == JsonValue::Object) {
      h.face.present = true;
      if (!f.Str(*fo, "names", "", h.face.names)) return false;
      Strings(fo->Get("sets"), h.face.sets);
      Strings(fo->Get("labels"), h.face.labels);
    }
  }
  return true;
}

bool ParseFrame(const JsonValue& o, Frame& fr, std::string& error) {
  Fields f{error};
  double index;
  if (!f.Num(o, "index", -1, index) || !f.Num(o, "pts", 0, fr.pts)) return false;
  fr.index = int64_t(index);
  const JsonValue* root = o.Get("root");
  if (!root || !f.ToVec(*root, fr.root, "frame.root")) {
    if (!root) error = "frame.root is missing";
    return false;
  }
  const JsonValue* rots = f.Kind(o, "rotations", JsonValue::Array, "an array");
  if (!rots) return false;
  fr.rotations.resize(rots->items.size());
  for (size_t j = 0; j < rots->items.size(); ++j)
    if (!f.ToQuat(rots->items[j], fr.rotations[j], "frame.rotations[" + std::to_string(j) + "]")) return false;
  fr.channels.clear();
  if (const JsonValue* cs = o.Get("channels")) {
    if (cs->kind == JsonValue::Object)
      for (size_t i = 0; i < cs->keys.size(); ++i) {
        const JsonValue& v = cs->items[i];
        if (v.kind != JsonValue::Array) continue;  // not values: a later revision's, ignored
        std::vector<double>& values = fr.channels[cs->keys[i]];
        for (const JsonValue& x : v.items) {
          if (x.kind != JsonValue::Number) { error = "frame.channels." + cs->keys[i] + " has a non-number"; return false; }
          values.push_back(x.n);
        }
      }
  }
  fr.face.clear();
  if (const JsonValue* fo = o.Get("face")) {
    if (fo->kind != JsonValue::Object) { error = "frame.face is not an object"; return false; }
    for (size_t i = 0; i < fo->keys.size(); ++i) {
      if (fo->items[i].kind != JsonValue::Number) { error = "frame.face." + fo->keys[i] + " is not a number"; return false; }
      fr.face[fo->keys[i]] = fo->items[i].n;
    }
  }
  return true;
}

// The wire is little-endian whatever the CPU is.
template <typename T>
T ReadLE(const uint8_t* p) {
  uint8_t b[sizeof(T)];
  const uint16_t probe = 1;
  const bool little = *reinterpret_cast<const uint8_t*>(&probe) == 1;
  for (size_t i = 0; i < sizeof(T); ++i) b[i] = little ? p[i] : p[sizeof(T) - 1 - i];
  T v;
  std::memcpy(&v, b, sizeof(T));
  return v;
}

}  // namespace

// ------------------------------------------------------------------ public API

Quat operator*(const Quat& a, const Quat& b) {
  return Quat{a.w * b.w - a.x * b.x - a.y * b.y - a.z * b.z, a.w * b.x + a.x * b.w + a.y * b.z - a.z * b.y,
              a.w * b.y - a.x * b.z + a.y * b.w + a.z * b.x, a.w * b.z + a.x * b.y - a.y * b.x + a.z * b.w};
}

Quat Conjugate(const Quat& q) { return Quat{q.w, -q.x, -q.y, -q.z}; }

int Skeleton::IndexOf(const std::string& joint) const {
  auto it = std::find(joints.begin(), joints.end(), joint);
  return it == joints.end() ? -1 : int(it - joints.begin());
}

bool ParseMessage(const std::string& text, Message& out, std::string& error) {
  JsonValue v;
  if (!ParseJson(text, v, error)) return false;
  if (v.kind != JsonValue::Object) { error = "message is not a JSON object"; return false; }
  Fields f{error};
  const JsonValue* type = v.Get("type");
  if (!type || type->kind != JsonValue::String) { error = "message has no \"type\" string"; return false; }
  out = Message();
  out.type_name = type->s;
  const std::string& t = type->s;
  if (t == "hello") { out.type = MessageType::Hello; return ParseHello(v, out.hello, error); }
  if (t == "frame") { out.type = MessageType::Frame; return ParseFrame(v, out.frame, error); }
  if (t == "channels") {
    out.type = MessageType::Channels;
    const JsonValue* cs = v.Get("channels");
    if (!cs) { error = "\"channels\" is missing or not an array"; return false; }
    return ParseChannels(*cs, "channels", out.channels, error);
  }
  if (t == "status") {
    out.type = MessageType::Status;
    double sent, dropped, clients;
    if (!f.Num(v, "latency_ms", 0, out.status.latency_ms) || !f.Num(v, "rtf", 0, out.status.rtf) ||
        !f.Num(v, "frames_sent", 0, sent) || !f.Num(v, "dropped", 0, dropped) || !f.Num(v, "clients", 0, clients))
      return false;
    out.status.frames_sent = int64_t(sent);
    out.status.dropped = int64_t(dropped);
    out.status.clients = int64_t(clients);
    return true;
  }
  if (t == "error") {
    out.type = MessageType::Error;
    return f.Str(v, "code", "", out.error_code) && f.Str(v, "message", "", out.error_message);
  }
  if (t == "end") {
    out.type = MessageType::End;
    double frames;
    if (!f.Num(v, "frames", 0, frames)) return false;
    out.end_frames = int64_t(frames);
    return true;
  }
  if (t == "resume") {
    out.type = MessageType::Resume;
    return f.Num(v, "backlog_s", 0, out.resume_backlog_s);
  }
  if (t == "goaway" || t == "session_resumed") {
    out.type = t == "goaway" ? MessageType::GoAway : MessageType::SessionResumed;
    double samples, frames;
    if (!f.Num(v, "samples", 0, samples) || !f.Num(v, "frames", 0, frames)) return false;
    out.handover_samples = int64_t(samples);
    out.handover_frames = int64_t(frames);
    return t == "session_resumed" || f.Str(v, "resume_token", "", out.resume_token);
  }
  out.type = t == "pong" ? MessageType::Pong : MessageType::Unknown;
  return true;
}

std::string ResumeSession(const std::string& token) {
  for (char c : token)
    if (!(std::isalnum(static_cast<unsigned char>(c)) || c == '-' || c == '_')) return std::string();
  return "{\"type\":\"resume_session\",\"token\":\"" + token + "\"}";
}

bool DecodeBinaryFrame(const uint8_t* data, size_t size, Frame& out, std::string& error, const Hello* hello) {
  size_t n = hello ? hello->skeleton.joints.size() : (size >= kBinaryHeaderBytes ? (size - kBinaryHeaderBytes) / 16 : 0);
  size_t end = kBinaryHeaderBytes + 16 * n;
  if (hello)
    for (const ChannelSpec& c : hello->channels) end = std::max(end, c.offset + 4 * c.size);
  if (size < end || (!hello && (size - kBinaryHeaderBytes) % 16 != 0)) {
    error = "binary frame of " + std::to_string(size) + " bytes is not 28 + 16*J" + (hello ? " + the hello's channels" : "");
    return false;
  }
  if (std::memcmp(data, "DGF1", 4) != 0) { error = "binary frame does not start with DGF1"; return false; }
  out.index = ReadLE<uint32_t>(data + 4);
  out.pts = ReadLE<double>(data + 8);
  out.root = Vec3{ReadLE<float>(data + 16), ReadLE<float>(data + 20), ReadLE<float>(data + 24)};
  out.rotations.resize(n);
  for (size_t j = 0; j < n; ++j) {
    const uint8_t* p = data + kBinaryHeaderBytes + 16 * j;
    out.rotations[j] = Quat{ReadLE<float>(p), ReadLE<float>(p + 4), ReadLE<float>(p + 8), ReadLE<float>(p + 12)};
  }
  out.channels.clear();
  out.face.clear();
  if (hello)
    for (const ChannelSpec& c : hello->channels) {
      std::vector<double>& values = out.channels[c.name];
      for (size_t i = 0; i < c.size; ++i) values.push_back(ReadLE<float>(data + c.offset + 4 * i));
      if (c.name == kFaceChannel && c.labels.size() == c.size)  // the face by name, as in a JSON frame
        for (size_t i = 0; i < c.size; ++i) out.face[c.labels[i]] = values[i];
    }
  return true;
}

static std::string QuotedJson(const std::string& text) {
  std::string s = "\"";
  for (char c : text) {
    if (c == '"' || c == '\\') s += '\\';
    if (static_cast<unsigned char>(c) < 0x20) { char b[8]; std::snprintf(b, sizeof b, "\\u%04x", c); s += b; continue; }
    s += c;
  }
  return s + '"';
}

std::string ClientHello(bool binary_frames, int audio_rate, const std::string& audio_format, int channels,
                        const std::string& face, const std::string& speaker) {
  std::string s = "{\"type\":\"hello\",\"protocol\":1,\"encoding\":\"";
  s += binary_frames ? "binary\"" : "json\"";
  // (escaped: the server answers an unknown set or speaker with the list of known ones)
  if (!face.empty()) s += ",\"face\":" + QuotedJson(face);
  if (!speaker.empty()) s += ",\"speaker\":" + QuotedJson(speaker);
  if (audio_rate > 0)
    s += ",\"audio\":{\"rate\":" + std::to_string(audio_rate) + ",\"format\":\"" + audio_format +
         "\",\"channels\":" + std::to_string(channels) + "}";
  return s + "}";
}

std::vector<Quat> GlobalRotations(const Skeleton& skeleton, const std::vector<Quat>& local) {
  std::vector<Quat> g;
  if (local.size() != skeleton.joints.size()) return g;
  g.resize(local.size());
  for (size_t j = 0; j < local.size(); ++j)
    g[j] = skeleton.parents[j] < 0 ? local[j] : g[size_t(skeleton.parents[j])] * local[j];
  return g;
}

Vec3 ToUnrealPosition(const Vec3& p, double unit_to_cm) { return Vec3{p.z * unit_to_cm, -p.x * unit_to_cm, p.y * unit_to_cm}; }
Quat ToUnrealRotation(const Quat& q) { return Quat{q.w, -q.z, q.x, -q.y}; }
Vec3 ToUnityPosition(const Vec3& p, double unit_to_m) { return Vec3{-p.x * unit_to_m, p.y * unit_to_m, p.z * unit_to_m}; }
Quat ToUnityRotation(const Quat& q) { return Quat{q.w, q.x, -q.y, -q.z}; }

}  // namespace dimgestor
