// Stand-ins for the UniVRM 0.x types DimgestorFace.cs uses with DIMGESTOR_UNIVRM (VRM.VRMBlendShapeProxy,
// BlendShapeKey, BlendShapePreset), with UniVRM's names and signatures, so that code path compiles and runs with
// mcs outside Unity. Keys compare as UniVRM's do: a preset by its preset, anything else by "Unknown_" + name.
// StubLog keeps what SetValues got and whether Apply followed. Never copy this file into a Unity project.
using System.Collections.Generic;
using UnityEngine;

namespace VRM
{
    public enum BlendShapePreset
    {
        Unknown, Neutral, A, I, U, E, O, Blink, Joy, Angry, Sorrow, Fun, LookUp, LookDown, LookLeft, LookRight, Blink_L, Blink_R,
    }

    public struct BlendShapeKey
    {
        public readonly BlendShapePreset Preset;
        readonly string id;
        public string Name { get; }

        BlendShapeKey(string name, BlendShapePreset preset)
        {
            Preset = preset;
            Name = preset != BlendShapePreset.Unknown ? preset.ToString() : name ?? "";
            id = preset != BlendShapePreset.Unknown ? Name : "Unknown_" + Name;
        }

        public static BlendShapeKey CreateFromPreset(BlendShapePreset preset) { return new BlendShapeKey("", preset); }
        public static BlendShapeKey CreateUnknown(string name) { return new BlendShapeKey(name, BlendShapePreset.Unknown); }
        public override string ToString() { return id; }
    }

    public class VRMBlendShapeProxy : MonoBehaviour
    {
        public List<string> StubLog = new List<string>();  // "id=value" per SetValues entry, "apply" per Apply
        public void SetValues(IEnumerable<KeyValuePair<BlendShapeKey, float>> values)
        {
            foreach (var kv in values) StubLog.Add(kv.Key + "=" + kv.Value.ToString("R", System.Globalization.CultureInfo.InvariantCulture));
        }
        public void Apply() { StubLog.Add("apply"); }
    }
}
