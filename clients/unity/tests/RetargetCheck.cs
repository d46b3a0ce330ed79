// Test driver: runs DimgestorClient's retargeting (Bind + Apply, the code LateUpdate runs) on frames recorded
// from a live server, with a stand-in humanoid avatar whose bones have other axes than the server skeleton
// (StubAvatar.cs: a random rest rotation per bone), whose root is turned by YAW degrees and whose arms are lowered by
// ARMS_DOWN degrees in its bind pose (0: a T-pose like the server skeleton's rest, 45: an A-pose). Prints each bone's
// position relative to the avatar root (metres), first in the bind pose ("rest") and then per frame;
// tests/test_clients_unity.py compares them with the server skeleton's forward kinematics in Unity space.
using System;
using System.Collections.Generic;
using System.Globalization;
using System.IO;
using System.Linq;
using System.Reflection;
using System.Text;
using Dimgestor;
using UnityEngine;

static class RetargetCheck
{
    static string N(float v) { return v.ToString("R", CultureInfo.InvariantCulture); }

    static int Main(string[] args)
    {
        if (args.Length != 3) { Console.Error.WriteLine("usage: RetargetCheck.exe FOLDER YAW_DEGREES ARMS_DOWN_DEGREES"); return 2; }
        Hello hello = null;
        var frames = new List<Frame>();
        foreach (var path in Directory.GetFiles(args[0]).OrderBy(p => p, StringComparer.Ordinal))
        {
            Message m = path.EndsWith(".bin") ? Protocol.DecodeBinaryFrame(File.ReadAllBytes(path), 0, (int)new FileInfo(path).Length)
                                              : (Message)Protocol.Parse(File.ReadAllText(path, Encoding.UTF8));
            if (m is Hello) hello = (Hello)m;
            else if (m is Frame) frames.Add((Frame)m);
        }
        var avatar = new StubAvatar(hello, float.Parse(args[1], CultureInfo.InvariantCulture), 7,
                                    float.Parse(args[2], CultureInfo.InvariantCulture));
        var root = avatar.Root;
        var animator = avatar.Animator;
        var byJoint = avatar.ByJoint;
        var names = avatar.Names;

        Func<string> bones = () => "\"bones\":{" + string.Join(",", byJoint.Select(kv =>
        {
            Vector3 v = Quaternion.Inverse(root.rotation) * (kv.Value.position - root.position);
            return "\"" + names[kv.Key] + "\":[" + N(v.x) + "," + N(v.y) + "," + N(v.z) + "]";
        })) + "}";
        Console.WriteLine("{\"rest\":true," + bones() + "}");

        var client = new DimgestorClient { animator = animator };
        var flags = BindingFlags.NonPublic | BindingFlags.Instance;
        typeof(DimgestorClient).GetMethod("Bind", flags).Invoke(client, new object[] { hello });
        var apply = typeof(DimgestorClient).GetMethod("Apply", flags);
        foreach (var f in frames)
        {
            apply.Invoke(client, new object[] { f });
            Console.WriteLine("{\"index\":" + f.Index + "," + bones() + "}");
        }
        return 0;
    }
}
