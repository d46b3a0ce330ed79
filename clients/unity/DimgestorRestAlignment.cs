// Rest alignment for the Unity client, in plain C# (no Unity dependency). An avatar's bind pose need not be the
// server skeleton's rest pose (a T-pose for ZEGGS/BEAT): many humanoids are bound in an A-pose. Per bound bone, A is
// the smallest rotation that turns the avatar's rest bone (the bone -> its main bound child) onto the skeleton's rest
// bone between the same two joints. DimgestorClient poses bone.rotation = root * delta * A * rest, so at rest the
// avatar takes the skeleton's rest pose (an A-posed avatar raises its arms) and then turns with it. Like the web
// viewer's VrmAvatar (clients/web/vrm-avatar.js); swing only, a bone's roll about itself is the avatar's own.
using System;

namespace Dimgestor
{
    public static class RestAlignment
    {
        static readonly string[] NotDirections = { "Jaw", "LeftEye", "RightEye" };  // children that do not say where a bone points
        static readonly string[] Centre = { "Hips", "Spine", "Chest", "UpperChest", "Neck", "Head" };
        static readonly string[] Fingers = { "Middle", "Index", "Ring", "Little", "Thumb" };  // the one a hand points along first
        const double Degenerate = 1e-6;  // a bone shorter than this (avatar or skeleton units) says no direction

        /// <summary>A per bone, as a rotation in the avatar root's space (Unity axes). bones: HumanBodyBones names; joints:
        /// their skeleton joints, in increasing order (parents before children); avatarRest: each bone's rest position
        /// in the avatar root's space. A bone without a bound child keeps its parent's A (a fingertip stays in line).</summary>
        public static Quat[] Compute(Skeleton sk, string[] bones, int[] joints, Vec3[] avatarRest)
        {
            Vec3[] source = Protocol.GlobalPositions(sk, Protocol.GlobalRotations(sk, sk.RestRotations));
            var parent = new int[joints.Length];  // nearest bound ancestor (-1: none)
            for (int k = 0; k < joints.Length; k++)
            {
                int j = sk.Parents[joints[k]];
                while (j >= 0 && Array.IndexOf(joints, j) < 0) j = sk.Parents[j];
                parent[k] = j < 0 ? -1 : Array.IndexOf(joints, j);
            }
            var align = new Quat[joints.Length];
            for (int k = 0; k < joints.Length; k++)
            {
                int c = MainChild(k, bones, parent);
                if (c < 0) { align[k] = parent[k] >= 0 ? align[parent[k]] : Quat.Identity; continue; }
                Vec3 s = Protocol.ToUnityPosition(source[joints[c]] - source[joints[k]], 1);
                align[k] = Swing(avatarRest[c] - avatarRest[k], s);
            }
            return align;
        }

        /// <summary>The bound child a bone points at: the spine or neck for the torso, the middle finger for a hand, else the first.</summary>
        static int MainChild(int k, string[] bones, int[] parent)
        {
            var kids = new System.Collections.Generic.List<int>();
            for (int c = k + 1; c < bones.Length; c++)
                if (parent[c] == k && Array.IndexOf(NotDirections, bones[c]) < 0) kids.Add(c);
            if (kids.Count == 0) return -1;
            if (Array.IndexOf(Centre, bones[k]) >= 0)
                foreach (int c in kids) if (Array.IndexOf(Centre, bones[c]) >= 0) return c;
            if (bones[k].EndsWith("Hand", StringComparison.Ordinal))
                foreach (string f in Fingers)
                    foreach (int c in kids) if (bones[c] == bones[k].Replace("Hand", f + "Proximal")) return c;
            return kids[0];
        }

        /// <summary>The smallest rotation turning direction a onto b; identity where either has no length.</summary>
        static Quat Swing(Vec3 a, Vec3 b)
        {
            double la = Length(a), lb = Length(b);
            if (la < Degenerate || lb < Degenerate) return Quat.Identity;
            a = a * (1 / la);
            b = b * (1 / lb);
            double d = a.X * b.X + a.Y * b.Y + a.Z * b.Z;
            Vec3 axis = 1 + d > 1e-9 ? Cross(a, b) : Cross(a, Math.Abs(a.X) < 0.9 ? new Vec3(1, 0, 0) : new Vec3(0, 1, 0));
            var q = new Quat(1 + d > 1e-9 ? 1 + d : 0, axis.X, axis.Y, axis.Z);  // opposite: half a turn about a perpendicular
            double n = Math.Sqrt(q.W * q.W + q.X * q.X + q.Y * q.Y + q.Z * q.Z);
            return new Quat(q.W / n, q.X / n, q.Y / n, q.Z / n);
        }

        static double Length(Vec3 v) { return Math.Sqrt(v.X * v.X + v.Y * v.Y + v.Z * v.Z); }
        static Vec3 Cross(Vec3 a, Vec3 b) { return new Vec3(a.Y * b.Z - a.Z * b.Y, a.Z * b.X - a.X * b.Z, a.X * b.Y - a.Y * b.X); }
    }
}
