// dimgestor protocol v1 revision 7 decoding (docs/protocol.md) in plain C#: no Unity dependency, so it compiles
// and is tested outside Unity (clients/unity/tests/). The Unity glue is DimgestorClient.cs.
//
// Spaces: the wire is BVH space (right-handed, Y up, file units). Unity is left-handed, Y up, metres:
//   position (x, y, z) -> (-x, y, z) * unitToMeters;  rotation (w, x, y, z) -> (w, x, -y, -z).
using System;
using System.Collections.Generic;
using System.Globalization;
using System.Text;

namespace Dimgestor
{
    public struct Vec3
    {
        public double X, Y, Z;
        public Vec3(double x, double y, double z) { X = x; Y = y; Z = z; }
        public static Vec3 operator +(Vec3 a, Vec3 b) { return new Vec3(a.X + b.X, a.Y + b.Y, a.Z + b.Z); }
        public static Vec3 operator -(Vec3 a, Vec3 b) { return new Vec3(a.X - b.X, a.Y - b.Y, a.Z - b.Z); }
        public static Vec3 operator *(Vec3 a, double s) { return new Vec3(a.X * s, a.Y * s, a.Z * s); }
    }

    /// <summary>Quaternion in (w, x, y, z) order, as on the wire.</summary>
    public struct Quat
    {
        public double W, X, Y, Z;
        public Quat(double w, double x, double y, double z) { W = w; X = x; Y = y; Z = z; }
        public static readonly Quat Identity = new Quat(1, 0, 0, 0);

        public static Quat operator *(Quat a, Quat b)
        {
            return new Quat(
                a.W * b.W - a.X * b.X - a.Y * b.Y - a.Z * b.Z,
                a.W * b.X + a.X * b.W + a.Y * b.Z - a.Z * b.Y,
                a.W * b.Y - a.X * b.Z + a.Y * b.W + a.Z * b.X,
                a.W * b.Z + a.X * b.Y - a.Y * b.X + a.Z * b.W);
        }

        public Quat Conjugate() { return new Quat(W, -X, -Y, -Z); }

        public Vec3 Rotate(Vec3 v)
        {
            Quat r = this * new Quat(0, v.X, v.Y, v.Z) * Conjugate();
            return new Vec3(r.X, r.Y, r.Z);
        }
    }

    public class Skeleton
    {
        public string[] Joints;
        public int[] Parents;          // -1 for the root; parents come before children
        public Vec3[] Offsets;         // rest offset from the parent, BVH space, file units
        public Quat[] RestRotations;   // rest local rotations (identity for BVH skeletons)
        public string Units = "cm";
        public double UnitToMeters = 0.01;

        public int IndexOf(string joint) { return Array.IndexOf(Joints, joint); }
    }

    public abstract class Message { public string Type; }

    public class Hello : Message
    {
        public int Protocol;
        public string Server;
        public double Fps;
        public string Encoding;
        public Skeleton Skeleton;
        public Dictionary<string, string> Humanoid = new Dictionary<string, string>();  // HumanBodyBones name -> joint
        public bool AudioAccepts;
        public int AudioRate;
        public string[] AudioFormats = new string[0];
        public double LookaheadS;
        public double WindowMs;  // optional: the server's inference window (frames arrive in bursts of it); 0 if absent
        public ChannelSpec[] Channels = new ChannelSpec[0];  // revision 6: what each frame carries beside the pose
        public FaceInfo Face;  // revision 7: the server makes a face (null: it does not)

        /// <summary>The same hello with another binary layout (a `channels` message's); this one is left as it is.</summary>
        public Hello WithChannels(ChannelSpec[] channels)
        {
            var h = (Hello)MemberwiseClone();
            h.Channels = channels;
            return h;
        }
    }

    /// <summary>Revision 7: hello.face, the server's face: the name set JSON frames use until the client asks for
    /// another (Names), the sets it knows, and the set's names in order.</summary>
    public class FaceInfo
    {
        public string Names = "";
        public string[] Sets = new string[0];
        public string[] Labels = new string[0];
    }

    /// <summary>Revision 6: one channel of every frame (e.g. blendshape weights): Size values, in a binary frame
    /// at byte Offset; Labels name each value when the server gives them (else empty).</summary>
    public class ChannelSpec
    {
        public string Name;
        public int Size, Offset;
        public string[] Labels = new string[0];
    }

    public class Frame : Message
    {
        public long Index;
        public double Pts;
        public Vec3 Root;              // root joint position, BVH space, file units
        public Quat[] Rotations;       // local rotations, skeleton order
        public Dictionary<string, double[]> Channels = new Dictionary<string, double[]>();  // revision 6: name -> values
        /// <summary>Revision 7: blendshape weight (0..1) by name, in the set the client asked for; empty without a face.</summary>
        public Dictionary<string, double> Face = new Dictionary<string, double>();
    }

    /// <summary>Revision 7: the binary frames' layout from the next frame on (the answer to a client hello's `face`).</summary>
    public class ChannelsMessage : Message { public ChannelSpec[] Channels = new ChannelSpec[0]; }

    public class Status : Message
    {
        public double LatencyMs, Rtf;
        public long FramesSent, Dropped, Clients;
    }

    public class ErrorMessage : Message
    {
        public string Code, Text;
        /// <summary>`slow_down` is a notice, not a failure: pause sending audio until `resume` (nothing was lost).</summary>
        public bool IsSlowDown { get { return Code == "slow_down"; } }
    }
    /// <summary>Revision 2: after a `slow_down`, the server's backlog of our audio is down to BacklogS: send again.</summary>
    public class Resume : Message { public double BacklogS; }
    /// <summary>Revision 3: the worker is stopping; our session's state is saved under Token (Samples of our audio at
    /// Rate, Frames made). Connect again, send resume_session with it, and re-send the audio from Samples on.</summary>
    public class GoAway : Message { public string Token; public long Samples, Frames; public int Rate; }
    /// <summary>Revision 3: resume_session worked; send our audio from Samples on (frames go on at Frames).</summary>
    public class SessionResumed : Message { public long Samples, Frames; public int Rate; }
    public class End : Message { public long Frames; }
    public class Pong : Message { }
    /// <summary>A type this client does not know; the protocol says to ignore it.</summary>
    public class UnknownMessage : Message { }

    /// <summary>One connection's decoding: it keeps the binary frames' layout, the hello's skeleton and channels, then
    /// each `channels` message's (revision 7: the face is laid out after the client asks for it). No I/O.</summary>
    public class MessageDecoder
    {
        public Hello Layout;  // null until the hello: binary frames are then read as rotations only

        public Message Text(string text)
        {
            var m = Protocol.Parse(text);
            if (m is Hello) Layout = (Hello)m;
            else if (m is ChannelsMessage && Layout != null) Layout = Layout.WithChannels(((ChannelsMessage)m).Channels);
            return m;
        }

        public Frame Binary(byte[] data, int offset, int count) { return Protocol.DecodeBinaryFrame(data, offset, count, Layout); }
    }

    public class ProtocolException : Exception
    {
        public ProtocolException(string message) : base(message) { }
    }

    public static class Protocol
    {
        public const int Version = 1;
        public const int Revision = 7;  // the optional additions this client knows (docs/protocol.md, "Revisions")
        public const int BinaryHeaderBytes = 28;  // "DGF1" | u32 index | f64 pts | f32[3] root
        public const string FaceChannel = "face";  // the binary layout's channel of the face (its labels name the values)

        /// <summary>Parse one text message. Throws ProtocolException (with the position) on bad input.</summary>
        public static Message Parse(string text)
        {
            object root = Json.Parse(text);
            var o = root as Dictionary<string, object>;
            if (o == null) throw new ProtocolException("message is not a JSON object");
            string type = Json.Str(o, "type", null);
            switch (type)
            {
                case "hello": return ParseHello(o);
                case "frame": return ParseFrame(o);
                case "channels": return new ChannelsMessage { Type = type, Channels = ParseChannels(Json.Arr(o, "channels"), "channels") };
                case "status":
                    return new Status
                    {
                        Type = type, LatencyMs = Json.Num(o, "latency_ms", 0), Rtf = Json.Num(o, "rtf", 0),
                        FramesSent = (long)Json.Num(o, "frames_sent", 0), Dropped = (long)Json.Num(o, "dropped", 0),
                        Clients = (long)Json.Num(o, "clients", 0),
                    };
                case "error": return new ErrorMessage { Type = type, Code = Json.Str(o, "code", ""), Text = Json.Str(o, "message", "") };
                case "end": return new End { Type = type, Frames = (long)Json.Num(o, "frames", 0) };
                case "pong": return new Pong { Type = type };
                case "resume": return new Resume { Type = type, BacklogS = Json.Num(o, "backlog_s", 0) };
                case "goaway":
                    return new GoAway
                    {
                        Type = type, Token = Json.Str(o, "resume_token", ""), Samples = (long)Json.Num(o, "samples", 0),
                        Frames = (long)Json.Num(o, "frames", 0), Rate = (int)Json.Num(o, "rate", 0),
                    };
                case "session_resumed":
                    return new SessionResumed
                    {
                        Type = type, Samples = (long)Json.Num(o, "samples", 0), Frames = (long)Json.Num(o, "frames", 0),
                        Rate = (int)Json.Num(o, "rate", 0),
                    };
                case null: throw new ProtocolException("message has no \"type\" field");
                default: return new UnknownMessage { Type = type };
            }
        }

        static Hello ParseHello(Dictionary<string, object> o)
        {
            var h = new Hello
            {
                Type = "hello", Protocol = (int)Json.Num(o, "protocol", 0), Server = Json.Str(o, "server", ""),
                Fps = Json.Num(o, "fps", 0), Encoding = Json.Str(o, "encoding", "json"),
                LookaheadS = Json.Num(o, "lookahead_s", 0), WindowMs = Json.Num(o, "window_ms", 0),
            };
            if (h.Protocol != Version)
                throw new ProtocolException("server speaks protocol " + h.Protocol + ", this client " + Version);
            var sk = Json.Obj(o, "skeleton");
            var s = new Skeleton();
            var joints = Json.Arr(sk, "joints");
            var parents = Json.Arr(sk, "parents");
            var offsets = Json.Arr(sk, "offsets");
            var rest = sk.ContainsKey("rest_rotations") ? Json.Arr(sk, "rest_rotations") : null;
            int n = joints.Count;
            if (parents.Count != n || offsets.Count != n || (rest != null && rest.Count != n))
                throw new ProtocolException("hello.skeleton: " + n + " joints but " + parents.Count + " parents, "
                    + offsets.Count + " offsets" + (rest != null ? ", " + rest.Count + " rest_rotations" : ""));
            s.Joints = new string[n]; s.Parents = new int[n]; s.Offsets = new Vec3[n]; s.RestRotations = new Quat[n];
            for (int j = 0; j < n; j++)
            {
                s.Joints[j] = joints[j] as string;
                if (s.Joints[j] == null) throw new ProtocolException("hello.skeleton.joints[" + j + "] is not a string");
                s.Parents[j] = (int)Json.ToNum(parents[j], "hello.skeleton.parents[" + j + "]");
                if (s.Parents[j] >= j || s.Parents[j] < -1) throw new ProtocolException("hello.skeleton.parents[" + j + "] = " + s.Parents[j] + ": parents must come before children");
                s.Offsets[j] = Vec(offsets[j], "hello.skeleton.offsets[" + j + "]");
                s.RestRotations[j] = rest != null ? Rot(rest[j], "hello.skeleton.rest_rotations[" + j + "]") : Quat.Identity;
            }
            s.Units = Json.Str(sk, "units", "cm");
            s.UnitToMeters = s.Units == "m" ? 1.0 : s.Units == "mm" ? 0.001 : 0.01;
            h.Skeleton = s;
            if (o.ContainsKey("humanoid"))
                foreach (var kv in Json.Obj(o, "humanoid"))
                    if (kv.Value is string) h.Humanoid[kv.Key] = (string)kv.Value;
            if (o.ContainsKey("audio"))
            {
                var a = Json.Obj(o, "audio");
                h.AudioAccepts = a.ContainsKey("accepts") && a["accepts"] is bool && (bool)a["accepts"];
                h.AudioRate = (int)Json.Num(a, "rate", 16000);
                if (a.ContainsKey("formats"))
                {
                    var f = Json.Arr(a, "formats");
                    h.AudioFormats = new string[f.Count];
                    for (int i = 0; i < f.Count; i++) h.AudioFormats[i] = f[i] as string;
                }
            }
            if (o.ContainsKey("channels")) h.Channels = ParseChannels(Json.Arr(o, "channels"), "hello.channels");
            if (o.ContainsKey("face") && o["face"] is Dictionary<string, object>)
            {
                var fo = (Dictionary<string, object>)o["face"];
                h.Face = new FaceInfo { Names = Json.Str(fo, "names", ""), Sets = Strings(fo, "sets"), Labels = Strings(fo, "labels") };
            }
            return h;
        }

        /// <summary>A binary layout (hello.channels or a `channels` message): each channel's name, size, byte offset, labels.</summary>
        static ChannelSpec[] ParseChannels(List<object> cs, string where)
        {
            var specs = new ChannelSpec[cs.Count];
            for (int i = 0; i < cs.Count; i++)
            {
                var c = cs[i] as Dictionary<string, object>;
                string what = where + "[" + i + "]";
                if (c == null) throw new ProtocolException(what + " is not an object");
                specs[i] = new ChannelSpec
                {
                    Name = Json.Str(c, "name", ""), Size = (int)Json.Num(c, "size", 0), Offset = (int)Json.Num(c, "offset", 0),
                    Labels = Strings(c, "labels"),
                };
                if (specs[i].Size < 0 || specs[i].Offset < 0) throw new ProtocolException(what + ": negative size or offset");
            }
            return specs;
        }

        static string[] Strings(Dictionary<string, object> o, string key)
        {
            if (!o.ContainsKey(key)) return new string[0];
            var l = Json.Arr(o, key);
            var s = new string[l.Count];
            for (int k = 0; k < l.Count; k++) s[k] = l[k] as string ?? "";
            return s;
        }

        static Frame ParseFrame(Dictionary<string, object> o)
        {
            var rots = Json.Arr(o, "rotations");
            var f = new Frame
            {
                Type = "frame", Index = (long)Json.Num(o, "index", -1), Pts = Json.Num(o, "pts", 0),
                Root = Vec(o.ContainsKey("root") ? o["root"] : null, "frame.root"), Rotations = new Quat[rots.Count],
            };
            for (int j = 0; j < rots.Count; j++) f.Rotations[j] = Rot(rots[j], "frame.rotations[" + j + "]");
            if (o.ContainsKey("channels"))
                foreach (var kv in Json.Obj(o, "channels"))
                {
                    var a = kv.Value as List<object>;
                    if (a == null) continue;  // not values: a later revision's, ignored
                    var values = new double[a.Count];
                    for (int i = 0; i < a.Count; i++) values[i] = Json.ToNum(a[i], "frame.channels." + kv.Key);
                    f.Channels[kv.Key] = values;
                }
            if (o.ContainsKey("face"))
                foreach (var kv in Json.Obj(o, "face"))
                    f.Face[kv.Key] = Json.ToNum(kv.Value, "frame.face." + kv.Key);
            return f;
        }

        static Vec3 Vec(object v, string what)
        {
            var a = v as List<object>;
            if (a == null || a.Count != 3) throw new ProtocolException(what + " is not [x, y, z]");
            return new Vec3(Json.ToNum(a[0], what), Json.ToNum(a[1], what), Json.ToNum(a[2], what));
        }

        static Quat Rot(object v, string what)
        {
            var a = v as List<object>;
            if (a == null || a.Count != 4) throw new ProtocolException(what + " is not [w, x, y, z]");
            return new Quat(Json.ToNum(a[0], what), Json.ToNum(a[1], what), Json.ToNum(a[2], what), Json.ToNum(a[3], what));
        }

        /// <summary>Decode a binary (DGF1) frame; count = message length in bytes. With the server's hello the
        /// frame has its joints' rotations, then each of hello.Channels at its offset (bytes past them are
        /// ignored); without it every byte after the header is a rotation (a frame without channels).</summary>
        public static Frame DecodeBinaryFrame(byte[] data, int offset, int count, Hello hello = null)
        {
            int n = hello != null ? hello.Skeleton.Joints.Length : (count - BinaryHeaderBytes) / 16;
            int end = BinaryHeaderBytes + 16 * n;
            if (hello != null) foreach (var c in hello.Channels) end = Math.Max(end, c.Offset + 4 * c.Size);
            if (count < end || (hello == null && (count - BinaryHeaderBytes) % 16 != 0))
                throw new ProtocolException("binary frame of " + count + " bytes is not 28 + 16*J" + (hello != null ? " + the hello's channels" : ""));
            if (data[offset] != 'D' || data[offset + 1] != 'G' || data[offset + 2] != 'F' || data[offset + 3] != '1')
                throw new ProtocolException("binary frame does not start with DGF1");
            var f = new Frame
            {
                Type = "frame", Index = ReadU32(data, offset + 4), Pts = ReadF64(data, offset + 8),
                Root = new Vec3(ReadF32(data, offset + 16), ReadF32(data, offset + 20), ReadF32(data, offset + 24)),
                Rotations = new Quat[n],
            };
            for (int j = 0, p = offset + BinaryHeaderBytes; j < n; j++, p += 16)
                f.Rotations[j] = new Quat(ReadF32(data, p), ReadF32(data, p + 4), ReadF32(data, p + 8), ReadF32(data, p + 12));
            if (hello != null)
                foreach (var c in hello.Channels)
                {
                    var values = new double[c.Size];
                    for (int i = 0; i < c.Size; i++) values[i] = ReadF32(data, offset + c.Offset + 4 * i);
                    f.Channels[c.Name] = values;
                    if (c.Name == FaceChannel && c.Labels.Length == c.Size)  // the face by name, as in a JSON frame
                        for (int i = 0; i < c.Size; i++) f.Face[c.Labels[i]] = values[i];
                }
            return f;
        }

        // The wire is little-endian whatever the CPU is.
        static byte[] LE(byte[] d, int p, int n)
        {
            var b = new byte[n];
            Array.Copy(d, p, b, 0, n);
            if (!BitConverter.IsLittleEndian) Array.Reverse(b);
            return b;
        }
        static long ReadU32(byte[] d, int p) { return BitConverter.ToUInt32(LE(d, p, 4), 0); }
        static double ReadF32(byte[] d, int p) { return BitConverter.ToSingle(LE(d, p, 4), 0); }
        static double ReadF64(byte[] d, int p) { return BitConverter.ToDouble(LE(d, p, 8), 0); }

        /// <summary>The client hello: frame encoding, when audio will be sent its format, (revision 7) the face's
        /// name set to receive ("vrm0", "vrm1", "arkit", "oculus"; "none": no face; null or "": the server's default)
        /// and (revision 9) the speaker whose style our sessions play (one of the hello's speakers; null or "": the
        /// server's default).</summary>
        public static string ClientHello(bool binaryFrames, int audioRate = 0, string audioFormat = "float32", int channels = 1,
                                         string face = null, string speaker = null)
        {
            var sb = new StringBuilder("{\"type\":\"hello\",\"protocol\":1,\"encoding\":\"");
            sb.Append(binaryFrames ? "binary" : "json").Append('"');
            if (!string.IsNullOrEmpty(face)) sb.Append(",\"face\":").Append(Json.Quote(face));
            if (!string.IsNullOrEmpty(speaker)) sb.Append(",\"speaker\":").Append(Json.Quote(speaker));
            if (audioRate > 0)
                sb.Append(",\"audio\":{\"rate\":").Append(audioRate.ToString(CultureInfo.InvariantCulture))
                  .Append(",\"format\":\"").Append(audioFormat).Append("\",\"channels\":")
                  .Append(channels.ToString(CultureInfo.InvariantCulture)).Append('}');
            return sb.Append('}').ToString();
        }

        /// <summary>resume_session with a goaway's token (URL-safe base64: nothing to escape).</summary>
        public static string ResumeSession(string token)
        {
            foreach (char c in token)
                if (!(char.IsLetterOrDigit(c) || c == '-' || c == '_')) throw new ProtocolException("resume token " + token + " is not URL-safe base64");
            return "{\"type\":\"resume_session\",\"token\":\"" + token + "\"}";
        }

        /// <summary>Float samples (-1..1) to the float32 little-endian wire format.</summary>
        public static byte[] EncodeFloat32(float[] samples, int start, int count)
        {
            var b = new byte[count * 4];
            for (int i = 0; i < count; i++)
            {
                var s = BitConverter.GetBytes(samples[start + i]);
                if (!BitConverter.IsLittleEndian) Array.Reverse(s);
                Array.Copy(s, 0, b, i * 4, 4);
            }
            return b;
        }

        // ---- spaces

        public static Vec3 ToUnityPosition(Vec3 p, double unitToMeters)
        {
            return new Vec3(-p.X * unitToMeters, p.Y * unitToMeters, p.Z * unitToMeters);
        }

        /// <summary>Mirror X: (w, x, y, z) -> (w, x, -y, -z). Unity's Quaternion(x, y, z, w) takes (X, Y, Z, W) of the result.</summary>
        public static Quat ToUnityRotation(Quat q) { return new Quat(q.W, q.X, -q.Y, -q.Z); }

        /// <summary>Global (model-space) rotation of every joint from local rotations: G[j] = G[parent] * L[j].</summary>
        public static Quat[] GlobalRotations(Skeleton s, Quat[] local)
        {
            if (local.Length != s.Joints.Length)
                throw new ProtocolException("frame has " + local.Length + " rotations for " + s.Joints.Length + " joints");
            var g = new Quat[local.Length];
            for (int j = 0; j < local.Length; j++)
                g[j] = s.Parents[j] < 0 ? local[j] : g[s.Parents[j]] * local[j];
            return g;
        }

        /// <summary>Global positions (BVH space, file units) of every joint from global rotations: the root at its offset.</summary>
        public static Vec3[] GlobalPositions(Skeleton s, Quat[] global)
        {
            var p = new Vec3[global.Length];
            for (int j = 0; j < global.Length; j++)
                p[j] = s.Parents[j] < 0 ? s.Offsets[j] : p[s.Parents[j]] + global[s.Parents[j]].Rotate(s.Offsets[j]);
            return p;
        }
    }
}
