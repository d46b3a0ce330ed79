// Test driver: decode recorded server messages (NNNNNN.json / NNNNNN.bin files in a folder, as saved by
// clients/python/client.py --save) with DimgestorProtocol and print one JSON line per message.
// tests/test_clients_unity.py compares the output with what the server sent.
using System;
using System.Globalization;
using System.IO;
using System.Linq;
using System.Text;
using Dimgestor;

static class DecodeRecorded
{
    static string N(double v) { return v.ToString("R", CultureInfo.InvariantCulture); }
    static string V(Vec3 v) { return "[" + N(v.X) + "," + N(v.Y) + "," + N(v.Z) + "]"; }
    static string Q(Quat q) { return "[" + N(q.W) + "," + N(q.X) + "," + N(q.Y) + "," + N(q.Z) + "]"; }
    static string Qs(Quat[] qs) { return "[" + string.Join(",", qs.Select(Q)) + "]"; }

    static int Main(string[] args)
    {
        if (args.Length != 1) { Console.Error.WriteLine("usage: DecodeRecorded.exe FOLDER"); return 2; }
        Skeleton skeleton = null;
        var decoder = new MessageDecoder();  // the binary frames' layout: the hello's, then each `channels` message's
        foreach (var path in Directory.GetFiles(args[0]).OrderBy(p => p, StringComparer.Ordinal))
        {
            Message m;
            try
            {
                if (path.EndsWith(".bin")) { var b = File.ReadAllBytes(path); m = decoder.Binary(b, 0, b.Length); }
                else if (path.EndsWith(".json")) m = decoder.Text(File.ReadAllText(path, Encoding.UTF8));
                else continue;
            }
            catch (ProtocolException e)
            {
                Console.WriteLine("{\"file\":\"" + Path.GetFileName(path) + "\",\"error\":\"" + e.Message.Replace("\\", "\\\\").Replace("\"", "\\\"") + "\"}");
                continue;
            }
            var sb = new StringBuilder("{\"file\":\"" + Path.GetFileName(path) + "\",\"type\":\"" + m.Type + "\"");
            var h = m as Hello;
            if (h != null)
            {
                skeleton = h.Skeleton;
                sb.Append(",\"joints\":" + h.Skeleton.Joints.Length + ",\"humanoid\":" + h.Humanoid.Count);
                sb.Append(",\"fps\":" + N(h.Fps) + ",\"unit_to_m\":" + N(h.Skeleton.UnitToMeters));
                sb.Append(",\"audio_rate\":" + h.AudioRate + ",\"offset_last\":" + V(h.Skeleton.Offsets[h.Skeleton.Offsets.Length - 1]));
                if (h.Face != null)
                    sb.Append(",\"face\":{\"names\":\"" + h.Face.Names + "\",\"sets\":[" + string.Join(",", h.Face.Sets.Select(x => "\"" + x + "\""))
                              + "],\"labels\":[" + string.Join(",", h.Face.Labels.Select(x => "\"" + x + "\"")) + "]}");
            }
            var cm = m as ChannelsMessage;
            if (cm != null)
            {
                sb.Append(",\"layout\":[" + string.Join(",", cm.Channels.Select(c => "[\"" + c.Name + "\"," + c.Size + "," + c.Offset + "]")) + "]");
            }
            var f = m as Frame;
            if (f != null)
            {
                sb.Append(",\"index\":" + f.Index + ",\"pts\":" + N(f.Pts) + ",\"root\":" + V(f.Root));
                sb.Append(",\"rotations\":" + Qs(f.Rotations));
                double u = skeleton != null ? skeleton.UnitToMeters : 0.01;
                sb.Append(",\"unity_root\":" + V(Protocol.ToUnityPosition(f.Root, u)));
                sb.Append(",\"unity_rotations\":" + Qs(f.Rotations.Select(Protocol.ToUnityRotation).ToArray()));
                if (skeleton != null) sb.Append(",\"global_rotations\":" + Qs(Protocol.GlobalRotations(skeleton, f.Rotations)));
                if (f.Channels.Count > 0)
                    sb.Append(",\"channels\":{" + string.Join(",", f.Channels.OrderBy(kv => kv.Key, StringComparer.Ordinal)
                        .Select(kv => "\"" + kv.Key + "\":[" + string.Join(",", kv.Value.Select(N)) + "]")) + "}");
                if (f.Face.Count > 0)
                    sb.Append(",\"face\":{" + string.Join(",", f.Face.OrderBy(kv => kv.Key, StringComparer.Ordinal)
                        .Select(kv => "\"" + kv.Key + "\":" + N(kv.Value))) + "}");
            }
            var st = m as Status;
            if (st != null) sb.Append(",\"latency_ms\":" + N(st.LatencyMs) + ",\"dropped\":" + st.Dropped);
            var end = m as End;
            if (end != null) sb.Append(",\"frames\":" + end.Frames);
            Console.WriteLine(sb.Append('}').ToString());
        }
        return 0;
    }
}
