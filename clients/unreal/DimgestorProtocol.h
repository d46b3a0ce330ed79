// dimgestor protocol v1 revision 7 decoding (docs/protocol.md) in engine-independent C++17: standard library only,
// no exceptions (Unreal builds without them), so it compiles and is tested outside the engine.
//
// The wire is BVH space: right-handed, Y up, file units (cm for ZEGGS). Conversions provided:
//   Unreal (left-handed, Z up, X forward, cm): position (x, y, z) -> (z, -x, y) * unit_to_cm
//                                               rotation (w, x, y, z) -> (w, -z, x, -y)
//   Unity  (left-handed, Y up, metres):       position (x, y, z) -> (-x, y, z) * unit_to_m
//                                               rotation (w, x, y, z) -> (w, x, -y, -z)
// (A change of axes M with det(M) = -1 maps a quaternion's vector part v to -M v.)
#pragma once

#include <cstddef>
#include <cstdint>
#include <map>
#include <string>
#include <vector>

namespace dimgestor {

struct Vec3 {
  double x = 0, y = 0, z = 0;
};

// Quaternion in (w, x, y, z) order, as on the wire.
struct Quat {
  double w = 1, x = 0, y = 0, z = 0;
};

Quat operator*(const Quat& a, const Quat& b);
Quat Conjugate(const Quat& q);

struct Skeleton {
  std::vector<std::string> joints;
  std::vector<int> parents;         // -1 for the root; parents come before children
  std::vector<Vec3> offsets;        // rest offset from the parent, BVH space, file units
  std::vector<Quat> rest_rotations; // rest local rotations (identity for BVH skeletons)
  std::string units = "cm";
  double unit_to_m = 0.01;

  int IndexOf(const std::string& joint) const;  // -1 when absent
};

// Revision 6: one channel of every frame (e.g. blendshape weights): `size` values, in a binary frame at byte
// `offset`; `labels` name each value when the server gives them (else empty).
struct ChannelSpec {
  std::string name;
  size_t size = 0, offset = 0;
  std::vector<std::string> labels;
};

// Revision 7: hello.face, the server's face: the name set JSON frames use until the client asks for another
// (`names`), the sets it knows, and the set's names in order. `present` is false when the server makes no face.
struct FaceInfo {
  bool present = false;
  std::string names;
  std::vector<std::string> sets, labels;
};

struct Hello {
  int protocol = 0;
  std::string server;
  double fps = 0;
  std::string encoding = "json";
  Skeleton skeleton;
  std::map<std::string, std::string> humanoid;  // Unity HumanBodyBones name -> joint name
  bool audio_accepts = false;
  int audio_rate = 16000;
  std::vector<std::string> audio_formats;
  double lookahead_s = 0;
  double window_ms = 0;  // optional: the server's inference window (frames arrive in bursts of it); 0 if absent
  std::vector<ChannelSpec> channels;  // revision 6: what each frame carries beside the pose
  FaceInfo face;                      // revision 7
};

struct Frame {
  int64_t index = -1;
  double pts = 0;
  Vec3 root;                  // root joint position, BVH space, file units
  std::vector<Quat> rotations;  // local rotations, skeleton order
  std::map<std::string, std::vector<double>> channels;  // revision 6: name -> values
  std::map<std::string, double> face;  // revision 7: blendshape weight (0..1) by name, in the set asked for; may be empty
};

struct Status {
  double latency_ms = 0, rtf = 0;
  int64_t frames_sent = 0, dropped = 0, clients = 0;
};

// Resume (revision 2): after a `slow_down` error (a notice, not a failure), the server takes our audio again.
// GoAway / SessionResumed (revision 3): the worker stops and saves our session under a token; we resume it on
// another worker and re-send our audio from `handover_samples` on.
// Channels (revision 7): the binary frames' layout from the next frame on (the answer to a client hello's "face").
enum class MessageType { Hello, Frame, Status, Error, End, Pong, Resume, GoAway, SessionResumed, Channels, Unknown };

// One decoded server message; only the member named by `type` is filled.
struct Message {
  MessageType type = MessageType::Unknown;
  std::string type_name;        // the wire "type" (kept for Unknown ones, which the protocol says to ignore)
  Hello hello;
  Frame frame;
  Status status;
  std::string error_code, error_message;  // error_code "slow_down": pause sending audio until Resume
  int64_t end_frames = 0;
  double resume_backlog_s = 0;  // Resume: seconds of our audio the server still has queued
  std::string resume_token;     // GoAway: the token for resume_session
  int64_t handover_samples = 0, handover_frames = 0;  // GoAway, SessionResumed: our audio (at our rate) / frames covered
  std::vector<ChannelSpec> channels;  // Channels: the new layout (replaces hello.channels for binary frames)
};

constexpr int kProtocolVersion = 1;
constexpr int kProtocolRevision = 7;  // the optional additions this client knows (docs/protocol.md, "Revisions")
constexpr size_t kBinaryHeaderBytes = 28;  // "DGF1" | u32 index | f64 pts | f32[3] root
constexpr const char* kFaceChannel = "face";  // the binary layout's channel of the face (its labels name the values)

// Parse one text message. On bad input returns false and says what and where in `error`.
bool ParseMessage(const std::string& text, Message& out, std::string& error);

// Decode one binary (DGF1) frame message of `size` bytes. With the server's hello the frame has its joints'
// rotations, then each of hello->channels at its offset (bytes past them are ignored; the "face" channel also fills
// `face` by its labels); without it every byte after the header is a rotation (a frame without channels). After a
// Channels message, decode with a hello whose `channels` are that message's.
bool DecodeBinaryFrame(const uint8_t* data, size_t size, Frame& out, std::string& error, const Hello* hello = nullptr);

// The client's hello; with audio_rate > 0 it also declares the audio format that will be sent, with a `face`
// (revision 7: "vrm0", "vrm1", "arkit", "oculus"; "none": no face) the face's name set to receive, and with a
// `speaker` (revision 9: one of the server's hello.speakers names) the speaker whose style our sessions play.
std::string ClientHello(bool binary_frames, int audio_rate = 0, const std::string& audio_format = "float32",
                        int channels = 1, const std::string& face = "", const std::string& speaker = "");

// resume_session with a goaway's token (URL-safe base64; anything else is refused: empty result).
std::string ResumeSession(const std::string& token);

// Global (model-space) rotations from local ones: G[j] = G[parent] * L[j]. Empty if the count is wrong.
std::vector<Quat> GlobalRotations(const Skeleton& skeleton, const std::vector<Quat>& local);

Vec3 ToUnrealPosition(const Vec3& p, double unit_to_cm);
Quat ToUnrealRotation(const Quat& q);
Vec3 ToUnityPosition(const Vec3& p, double unit_to_m);
Quat ToUnityRotation(const Quat& q);

}  // namespace dimgestor
