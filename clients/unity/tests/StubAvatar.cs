// A stand-in humanoid avatar for the Unity client tests: one Transform per bone of the server's humanoid map,
// parented to the nearest mapped ancestor, with the server skeleton's rest geometry (in Unity space) but
// every bone with its own random axes, under a root turned by a yaw, like a real rig differs from the
// training skeleton. With armsDownDegrees its bind pose is an A-pose: each arm (the upper arm and all below it)
// turned down by that angle about the facing axis at the upper arm joint.
using System;
using System.Collections.Generic;
using System.Linq;
using Dimgestor;
using UnityEngine;

class StubAvatar
{
    public readonly Transform Root;
    public readonly Animator Animator;
    public readonly Dictionary<int, Transform> ByJoint = new Dictionary<int, Transform>();  // server joint -> bone
    public readonly Dictionary<int, string> Names = new Dictionary<int, string>();          // server joint -> HumanBodyBones name

    public StubAvatar(Hello hello, float yawDegrees, int seed, float armsDownDegrees = 0)
    {
        var sk = hello.Skeleton;
        var restPos = Protocol.GlobalPositions(sk, Protocol.GlobalRotations(sk, sk.RestRotations));

        float yaw = yawDegrees * (float)Math.PI / 180f;
        Root = new Transform { localRotation = new Quaternion(0, (float)Math.Sin(yaw / 2), 0, (float)Math.Cos(yaw / 2)), localPosition = new Vector3(1, 0, -2) };
        Animator = new Animator { StubTransform = Root };
        var rng = new System.Random(seed);
        foreach (var kv in hello.Humanoid.OrderBy(kv => sk.IndexOf(kv.Value)))
        {
            int j = sk.IndexOf(kv.Value);
            HumanBodyBones id;
            if (j < 0 || !Enum.TryParse(kv.Key, out id)) continue;
            int p = sk.Parents[j];
            while (p >= 0 && !ByJoint.ContainsKey(p)) p = sk.Parents[p];
            var t = new Transform { parent = p >= 0 ? ByJoint[p] : Root };
            Vec3 u = Protocol.ToUnityPosition(restPos[j], sk.UnitToMeters);
            t.position = Root.position + Root.rotation * new Vector3((float)u.X, (float)u.Y, (float)u.Z);
            t.rotation = Root.rotation * RandomRotation(rng);
            ByJoint[j] = t;
            Names[j] = kv.Key;
            Animator.StubBones[id] = t;
        }
        var arms = new[] { new[] { HumanBodyBones.LeftUpperArm, HumanBodyBones.LeftLowerArm },
                           new[] { HumanBodyBones.RightUpperArm, HumanBodyBones.RightLowerArm } };
        foreach (var arm in arms)
        {
            Transform upper = Animator.GetBoneTransform(arm[0]), lower = Animator.GetBoneTransform(arm[1]);
            if (upper == null || lower == null || armsDownDegrees == 0) continue;
            Vector3 along = Quaternion.Inverse(Root.rotation) * (lower.position - upper.position);
            float down = -Math.Sign(along.x) * armsDownDegrees * (float)Math.PI / 180f;  // about +Z: +X turns towards +Y
            var turn = new Quaternion(0, 0, (float)Math.Sin(down / 2), (float)Math.Cos(down / 2));
            upper.rotation = Root.rotation * turn * Quaternion.Inverse(Root.rotation) * upper.rotation;  // its children follow
        }
    }

    static Quaternion RandomRotation(System.Random rng)
    {
        double a = rng.NextDouble() * 2 * Math.PI, b = rng.NextDouble() * 2 * Math.PI, u = rng.NextDouble();
        double s1 = Math.Sqrt(1 - u), s2 = Math.Sqrt(u);  // uniform on the unit sphere of quaternions
        return new Quaternion((float)(s1 * Math.Sin(a)), (float)(s1 * Math.Cos(a)), (float)(s2 * Math.Sin(b)), (float)(s2 * Math.Cos(b)));
    }
}
