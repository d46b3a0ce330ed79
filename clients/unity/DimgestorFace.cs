// The face (protocol revision 7) on a Unity avatar: each frame's blendshape weights (0..1 by name, in the name set
// the client asked for) set on SkinnedMeshRenderers through a name map, and with UniVRM on a VRM 0.x model's
// VRMBlendShapeProxy. DimgestorClient calls Apply with the frame it shows, so the face moves with the body.
//
// UniVRM is optional: its code path compiles only with the scripting define symbol DIMGESTOR_UNIVRM (Player >
// Other Settings > Scripting Define Symbols), so a project without UniVRM builds as it is.
using System;
using System.Collections.Generic;
using UnityEngine;

namespace Dimgestor
{
    /// <summary>One entry of the face name map: the server's face name -> a blendshape of your mesh (or a VRM
    /// BlendShapeClip's name). One face name may drive several blendshapes.</summary>
    [Serializable]
    public class FaceName
    {
        [Tooltip("A name of the face set you asked for, e.g. A, Blink (vrm0) or jawOpen (arkit)")]
        public string face = "";
        [Tooltip("Your mesh's blendshape (or VRM BlendShapeClip) it drives, e.g. Fcl_MTH_A")]
        public string blendShape = "";
    }

    /// <summary>Sets face weights on blendshapes by name. Which blendshapes a face name drives is worked out once per
    /// renderer and name: the map's entries for it (else the name itself), each found by exact name, then ignoring
    /// case, then as the part after a '.' (FBX exports name them "blendShape1.jawOpen"). Not thread-safe.</summary>
    public class FaceApplier
    {
        public float Scale = 100f;  // Unity blendshape weights run 0..100
        readonly Dictionary<SkinnedMeshRenderer, Dictionary<string, int[]>> indices = new Dictionary<SkinnedMeshRenderer, Dictionary<string, int[]>>();
        readonly SortedSet<string> unmatched = new SortedSet<string>(StringComparer.Ordinal);

        /// <summary>Face names that drive nothing on any renderer, comma-separated (to show in the inspector).</summary>
        public string Unmatched { get { return string.Join(", ", unmatched); } }

        /// <summary>Forget what was worked out (another mesh, map or name set).</summary>
        public void Reset() { indices.Clear(); unmatched.Clear(); }

        public void Apply(Dictionary<string, double> face, SkinnedMeshRenderer[] renderers, FaceName[] map)
        {
            if (renderers == null) return;
            foreach (var kv in face)
            {
                bool found = false;
                foreach (var r in renderers)
                {
                    if (r == null || r.sharedMesh == null) continue;
                    foreach (int i in IndicesOf(r, kv.Key, map))
                    {
                        r.SetBlendShapeWeight(i, (float)(Clamp01(kv.Value) * Scale));
                        found = true;
                    }
                }
                if (!found) unmatched.Add(kv.Key);
                else unmatched.Remove(kv.Key);
            }
        }

        int[] IndicesOf(SkinnedMeshRenderer r, string name, FaceName[] map)
        {
            Dictionary<string, int[]> byName;
            if (!indices.TryGetValue(r, out byName)) indices[r] = byName = new Dictionary<string, int[]>();
            int[] found;
            if (!byName.TryGetValue(name, out found)) byName[name] = found = Resolve(r.sharedMesh, Targets(name, map));
            return found;
        }

        /// <summary>What a face name drives: its entries in the map, else the name itself.</summary>
        public static List<string> Targets(string name, FaceName[] map)
        {
            var targets = new List<string>();
            if (map != null)
                foreach (var m in map)
                    if (m != null && m.face == name && !string.IsNullOrEmpty(m.blendShape)) targets.Add(m.blendShape);
            if (targets.Count == 0) targets.Add(name);
            return targets;
        }

        /// <summary>The mesh's blendshape indices of these names (exact, then ignoring case, then after a '.').</summary>
        public static int[] Resolve(Mesh mesh, List<string> names)
        {
            var found = new List<int>();
            foreach (var name in names)
            {
                int i = mesh.GetBlendShapeIndex(name);
                for (int k = 0; i < 0 && k < mesh.blendShapeCount; k++)
                    if (string.Equals(mesh.GetBlendShapeName(k), name, StringComparison.OrdinalIgnoreCase)) i = k;
                for (int k = 0; i < 0 && k < mesh.blendShapeCount; k++)
                {
                    string s = mesh.GetBlendShapeName(k);
                    int dot = s.LastIndexOf('.');
                    if (dot >= 0 && string.Equals(s.Substring(dot + 1), name, StringComparison.OrdinalIgnoreCase)) i = k;
                }
                if (i >= 0 && !found.Contains(i)) found.Add(i);
            }
            return found.ToArray();
        }

        static double Clamp01(double w) { return w < 0 ? 0 : w > 1 ? 1 : w; }

#if DIMGESTOR_UNIVRM
        /// <summary>A VRM 0.x model (UniVRM): each face name (through the map) as a BlendShapeClip, preset names (A, I,
        /// U, E, O, Blink, Blink_L, Blink_R, Joy: the "vrm0" set) as their presets, others as custom clips by name.</summary>
        public static void ApplyVrm(Dictionary<string, double> face, VRM.VRMBlendShapeProxy proxy, FaceName[] map)
        {
            if (proxy == null) return;
            var values = new List<KeyValuePair<VRM.BlendShapeKey, float>>();
            foreach (var kv in face)
                foreach (var clip in Targets(kv.Key, map))
                    values.Add(new KeyValuePair<VRM.BlendShapeKey, float>(VrmKey(clip), (float)Clamp01(kv.Value)));
            proxy.SetValues(values);
            proxy.Apply();  // (some UniVRM versions' SetValues only accumulates)
        }

        public static VRM.BlendShapeKey VrmKey(string clip)
        {
            VRM.BlendShapePreset preset;
            bool isPreset = Enum.TryParse(clip, out preset) && preset != VRM.BlendShapePreset.Unknown && !char.IsDigit(clip[0]);
            return isPreset ? VRM.BlendShapeKey.CreateFromPreset(preset) : VRM.BlendShapeKey.CreateUnknown(clip);
        }
#endif
    }
}
