// Playout buffer: the server computes motion window by window, so frames arrive in bursts (e.g. 4 frames
// every 200 ms). Applying each on arrival would animate at 5 fps; instead every frame is shown at its own
// presentation time, pts + offset on the local clock, interpolating between neighbours (root: linear,
// rotations: slerp, face weights: linear, so the mouth moves with the body). The same rules are in
// clients/web/playout.js and clients/unreal/DimgestorPlayout.h.
//
// Offset is set when a stream starts (first frame shown Delay seconds after it arrived), grows when a frame
// arrives too late to be shown on time, and shrinks when more than 2 x Delay is buffered. Plain C#, no
// Unity dependency; not thread-safe (push and sample from one thread, e.g. under the client's lock).
using System;
using System.Collections.Generic;

namespace Dimgestor
{
    public class FramePlayout
    {
        const int MaxQueue = 256;
        const double LateMarginS = 0.02;

        public double DelayS;
        public double? Offset;        // local seconds minus pts; null until a stream starts
        public int Reanchors;         // times the clock was moved because frames came late or piled up
        readonly List<Frame> queue = new List<Frame>();

        public FramePlayout(double delayS = 0.3) { DelayS = delayS; }

        public int Count { get { return queue.Count; } }

        /// <summary>Forget everything: the next frame starts a new playout clock.</summary>
        public void Reset() { queue.Clear(); Offset = null; }

        /// <summary>Add a frame that arrived at local time now (seconds).</summary>
        public void Push(Frame f, double now)
        {
            Frame last = queue.Count > 0 ? queue[queue.Count - 1] : null;
            if (Offset == null || (last != null && (f.Index < last.Index || f.Pts <= last.Pts)))
            {
                queue.Clear();  // a new stream (own audio session, --loop, reconnect)
                Offset = now - f.Pts + DelayS;
            }
            else if (now - Offset.Value > f.Pts)
            {
                Offset = now - f.Pts + LateMarginS;  // late: show it now, and keep that much more buffer
                Reanchors++;
            }
            else if (f.Pts - (now - Offset.Value) > 2 * DelayS)
            {
                Offset = now - f.Pts + DelayS;  // too much buffered: catch up
                Reanchors++;
            }
            queue.Add(f);
            if (queue.Count > MaxQueue) queue.RemoveAt(0);
        }

        /// <summary>The pose to show at local time now, interpolated; null before any frame.</summary>
        public Frame Sample(double now)
        {
            if (queue.Count == 0) return null;
            double t = now - Offset.Value;
            while (queue.Count > 1 && queue[1].Pts <= t) queue.RemoveAt(0);  // keep the last frame at or before t
            Frame a = queue[0];
            if (queue.Count == 1 || t <= a.Pts || queue[1].Rotations.Length != a.Rotations.Length) return a;
            Frame b = queue[1];
            double u = (t - a.Pts) / (b.Pts - a.Pts);
            var r = new Frame { Type = "frame", Index = a.Index, Pts = t, Root = a.Root + (b.Root - a.Root) * u,
                                Rotations = new Quat[a.Rotations.Length] };
            for (int j = 0; j < r.Rotations.Length; j++) r.Rotations[j] = Slerp(a.Rotations[j], b.Rotations[j], u);
            r.Face = LerpFace(a.Face, b.Face, u);
            return r;
        }

        /// <summary>Face weights between two frames; a name the later frame lacks (another set) keeps a's weight.</summary>
        public static Dictionary<string, double> LerpFace(Dictionary<string, double> a, Dictionary<string, double> b, double u)
        {
            var r = new Dictionary<string, double>(a.Count);
            foreach (var kv in a)
            {
                double w;
                r[kv.Key] = b.TryGetValue(kv.Key, out w) ? kv.Value + (w - kv.Value) * u : kv.Value;
            }
            return r;
        }

        /// <summary>Spherical interpolation of unit quaternions along the shorter arc.</summary>
        public static Quat Slerp(Quat a, Quat b, double u)
        {
            double dot = a.W * b.W + a.X * b.X + a.Y * b.Y + a.Z * b.Z;
            double s = dot < 0 ? -1 : 1;  // q and -q are the same rotation: take the nearer one
            dot *= s;
            double wa, wb;
            if (dot > 0.9995) { wa = 1 - u; wb = u; }  // nearly equal: linear is exact enough and avoids 0/0
            else
            {
                double th = Math.Acos(dot), sin = Math.Sin(th);
                wa = Math.Sin((1 - u) * th) / sin;
                wb = Math.Sin(u * th) / sin;
            }
            var r = new Quat(wa * a.W + wb * s * b.W, wa * a.X + wb * s * b.X, wa * a.Y + wb * s * b.Y, wa * a.Z + wb * s * b.Z);
            double n = Math.Sqrt(r.W * r.W + r.X * r.X + r.Y * r.Y + r.Z * r.Z);
            return new Quat(r.W / n, r.X / n, r.Y / n, r.Z / n);
        }
    }
}
