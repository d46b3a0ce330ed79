// Test driver: runs DimgestorClient's retargeting (Bind + Apply, the code LateUpdate runs) on frames recorded
// from a live server, with a stand-in humanoid avatar whose bones have other axes than the server skeleton
// (a random rest rotation per bone) and whose root is turned by YAW degrees. Prints, per frame, each bone's
// position relative to the avatar root (metres); tests/test_clients_unity.py compares them with the
// server skeleton's forward kinematics in Unity space.
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

    static Quaternion RandomRotation(System.Random rng)
    {
        double a = rng.NextDouble() * 2 * Math.PI, b = rng.NextDouble() * 2 * Math.PI, u = rng.NextDouble();
        double s1 = Math.Sqrt(1 - u), s2 = Math.Sqrt(u);  // uniform on the unit sphere of quaternions
        return new Quaternion((float)(s1 * Math.Sin(a)), (float)(s1 * Math.Cos(a)), (float)(s2 * Math.Sin(b)), (float)(s2 * Math.Cos(b)));
    }

    static int Main(string[] args)
    {
        if (args.Length != 2) { Console.Error.WriteLine("usage: RetargetCheck.exe FOLDER YAW_DEGREES"); return 2; }
        Hello hello = null;
        var frames = new List<Frame>();
        foreach (var path in Directory.GetFiles(args[0]).OrderBy(p => p, StringComparer.Ordinal))
        {
            Message m = path.EndsWith(".bin") ? Protocol.DecodeBinaryFrame(File.ReadAllBytes(path), 0, (int)new FileInfo(path).Length)
                                              : (Message)Protocol.Parse(File.ReadAllText(path, Encoding.UTF8));
            if (m is Hello) hello = (Hello)m;
            else if (m is Frame) frames.Add((Frame)m);
        }
        var sk = hello.Skeleton;

        // Rest pose of the server skeleton in Unity space, metres.
        var restGlobal = Protocol.GlobalRotations(sk, sk.RestRotations);
        var restPos = new Vec3[sk.Joints.Length];
        for (int j = 0; j < sk.Joints.Length; j++)
            restPos[j] = sk.Parents[j] < 0 ? sk.Offsets[j] : restPos[sk.Parents[j]] + restGlobal[sk.Parents[j]].Rotate(sk.Offsets[j]);

        // The avatar: one Transform per mapped bone, parented to the nearest mapped ancestor, same rest
        // geometry, but every bone with its own (random) axes.
        float yaw = float.Parse(args[1], CultureInfo.InvariantCulture) * (float)Math.PI / 180f;
        var root = new Transform { localRotation = new Quaternion(0, (float)Math.Sin(yaw / 2), 0, (float)Math.Cos(yaw / 2)), localPosition = new Vector3(1, 0, -2) };
        var animator = new Animator { StubTransform = root };
        var byJoint = new Dictionary<int, Transform>();
        var names = new Dictionary<int, string>();
        var rng = new System.Random(7);
        foreach (var kv in hello.Humanoid.OrderBy(kv => sk.IndexOf(kv.Value)))
        {
            int j = sk.IndexOf(kv.Value);
            HumanBodyBones id;
            if (j < 0 || !Enum.TryParse(kv.Key, out id)) continue;
            int p = sk.Parents[j];
            while (p >= 0 && !byJoint.ContainsKey(p)) p = sk.Parents[p];
            var t = new Transform { parent = p >= 0 ? byJoint[p] : root };
            Vec3 u = Protocol.ToUnityPosition(restPos[j], sk.UnitToMeters);
            t.position = root.position + root.rotation * new Vector3((float)u.X, (float)u.Y, (float)u.Z);
            t.rotation = root.rotation * RandomRotation(rng);
            byJoint[j] = t;
            names[j] = kv.Key;
            animator.StubBones[id] = t;
        }

        var client = new DimgestorClient { animator = animator };
        var flags = BindingFlags.NonPublic | BindingFlags.Instance;
        typeof(DimgestorClient).GetMethod("Bind", flags).Invoke(client, new object[] { hello });
        var apply = typeof(DimgestorClient).GetMethod("Apply", flags);
        foreach (var f in frames)
        {
            apply.Invoke(client, new object[] { f });
            var sb = new StringBuilder("{\"index\":" + f.Index + ",\"bones\":{");
            sb.Append(string.Join(",", byJoint.Select(kv =>
            {
                Vector3 v = Quaternion.Inverse(root.rotation) * (kv.Value.position - root.position);
                return "\"" + names[kv.Key] + "\":[" + N(v.x) + "," + N(v.y) + "," + N(v.z) + "]";
            })));
            Console.WriteLine(sb.Append("}}").ToString());
        }
        return 0;
    }
}
