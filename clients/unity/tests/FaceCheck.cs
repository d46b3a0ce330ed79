// Test driver: the face (protocol revision 7) through DimgestorClient as LateUpdate shows it. Decodes recorded server
// messages (NNNNNN.json / .bin in FOLDER) with MessageDecoder, plays the frames out with FramePlayout (each pushed at
// its pts, on time) and at each of SPEC's times applies the interpolated frame with the client's ApplyFace to stand-in
// SkinnedMeshRenderers (SPEC's blendshape names and face name map), and with DIMGESTOR_UNIVRM to a stand-in
// VRMBlendShapeProxy. SPEC is JSON: {"meshes": [[blendshape names], ...], "map": [[face, blendShape], ...],
// "times": [pts, ...], "vrm": bool}. Notices (error messages) go to the client's own message handler. Prints one JSON
// line per time (with the client's faceWithheld, faceNotice and lastError); tests/test_clients_unity.py checks them.
using System;
using System.Collections.Generic;
using System.Globalization;
using System.IO;
using System.Linq;
using System.Reflection;
using System.Text;
using Dimgestor;
using UnityEngine;

static class FaceCheck
{
    static string N(double v) { return v.ToString("R", CultureInfo.InvariantCulture); }

    static int Main(string[] args)
    {
        if (args.Length != 2) { Console.Error.WriteLine("usage: FaceCheck.exe FOLDER SPEC"); return 2; }
        var decoder = new MessageDecoder();
        var frames = new List<Frame>();
        var notices = new List<Message>();
        foreach (var path in Directory.GetFiles(args[0]).OrderBy(p => p, StringComparer.Ordinal))
        {
            var b = File.ReadAllBytes(path);
            Message m = path.EndsWith(".bin") ? decoder.Binary(b, 0, b.Length) : decoder.Text(Encoding.UTF8.GetString(b));
            if (m is Frame) frames.Add((Frame)m);
            if (m is ErrorMessage) notices.Add(m);
        }
        var spec = (Dictionary<string, object>)Json.Parse(File.ReadAllText(args[1], Encoding.UTF8));
        var meshes = Json.Arr(spec, "meshes").Select(names => new SkinnedMeshRenderer
        {
            sharedMesh = new Mesh { StubBlendShapes = ((List<object>)names).Cast<string>().ToList() },
        }).ToArray();
        var client = new DimgestorClient
        {
            faceMeshes = meshes,
            faceNameMap = Json.Arr(spec, "map").Cast<List<object>>().Select(e => new FaceName { face = (string)e[0], blendShape = (string)e[1] }).ToArray(),
        };
#if DIMGESTOR_UNIVRM
        var proxy = new VRM.VRMBlendShapeProxy();
        if (spec.ContainsKey("vrm") && (bool)spec["vrm"]) client.vrmBlendShapeProxy = proxy;
#endif
        var applyFace = typeof(DimgestorClient).GetMethod("ApplyFace", BindingFlags.NonPublic | BindingFlags.Instance);
        var handle = typeof(DimgestorClient).GetMethod("Handle", BindingFlags.NonPublic | BindingFlags.Instance);
        foreach (var m in notices) handle.Invoke(client, new object[] { m });

        // What the client asks for: the face set in its hello, with and without audio (a name is escaped, not trusted).
        Console.WriteLine("{\"hellos\":[" + Protocol.ClientHello(true, face: "arkit") + "," + Protocol.ClientHello(false, 48000, "float32", 2, "vrm0")
                          + "," + Protocol.ClientHello(true, face: "a\"b\\") + "," + Protocol.ClientHello(true)
                          + "," + Protocol.ClientHello(false, speaker: "sc\"ott") + "]}");

        var playout = new FramePlayout(0.3);
        foreach (var f in frames) playout.Push(f, f.Pts);  // each on time: shown DelayS after its pts
        foreach (var t in Json.Arr(spec, "times").Select(x => (double)x))
        {
            Frame f = playout.Sample(t + playout.DelayS);
            applyFace.Invoke(client, new object[] { f });
            var sb = new StringBuilder("{\"t\":" + N(t) + ",\"index\":" + f.Index + ",\"root\":[" + N(f.Root.X) + "," + N(f.Root.Y) + "," + N(f.Root.Z) + "]");
            sb.Append(",\"face\":{" + string.Join(",", f.Face.OrderBy(kv => kv.Key, StringComparer.Ordinal).Select(kv => "\"" + kv.Key + "\":" + N(kv.Value))) + "}");
            sb.Append(",\"weights\":[" + string.Join(",", meshes.Select(r => "{" + string.Join(",", r.StubWeights.OrderBy(kv => kv.Key)
                .Select(kv => "\"" + r.sharedMesh.GetBlendShapeName(kv.Key) + "\":" + N(kv.Value))) + "}")) + "]");
            sb.Append(",\"unmatched\":\"" + client.faceUnmatched + "\"");
            sb.Append(",\"withheld\":" + (client.faceWithheld ? "true" : "false") + ",\"face_notice\":\"" + client.faceNotice
                      + "\",\"last_error\":\"" + client.lastError + "\"");
#if DIMGESTOR_UNIVRM
            sb.Append(",\"vrm\":[" + string.Join(",", proxy.StubLog.Select(x => "\"" + x + "\"")) + "]");
            proxy.StubLog.Clear();
#endif
            Console.WriteLine(sb.Append('}').ToString());
        }
        return 0;
    }
}
