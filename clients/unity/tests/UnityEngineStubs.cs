// Minimal stand-ins for the few UnityEngine types DimgestorClient.cs uses, with Unity's names and
// signatures, so the MonoBehaviour compiles with mcs outside Unity, plus just enough behaviour (a
// rotation/translation transform hierarchy, quaternion maths, humanoid bone lookup) for the retarget test
// (RetargetCheck.cs). Members named Stub* exist only here. Never copy this file into a Unity project.
using System;
using System.Collections.Generic;

namespace UnityEngine
{
    public class Object { }

    public class Component : Object
    {
        public Transform StubTransform;  // what `transform` returns for non-Transform components
        public Transform transform { get { return this as Transform ?? StubTransform; } }
        public T GetComponent<T>() { return default(T); }
    }

    public class Debug
    {
        public static void LogWarning(object message) { Console.Error.WriteLine(message); }
    }

    public class Behaviour : Component { public bool enabled { get; set; } }
    public class MonoBehaviour : Behaviour { }

    /// <summary>Rotation and translation only (no scale), like a Unity Transform with unit scale.</summary>
    public class Transform : Component
    {
        public Transform parent { get; set; }
        public Vector3 localPosition { get; set; }
        public Quaternion localRotation { get; set; } = Quaternion.identity;

        public Quaternion rotation
        {
            get { return parent == null ? localRotation : parent.rotation * localRotation; }
            set { localRotation = parent == null ? value : Quaternion.Inverse(parent.rotation) * value; }
        }

        public Vector3 position
        {
            get { return parent == null ? localPosition : parent.position + parent.rotation * localPosition; }
            set { localPosition = parent == null ? value : Quaternion.Inverse(parent.rotation) * (value - parent.position); }
        }

        public Vector3 InverseTransformPoint(Vector3 p) { return Quaternion.Inverse(rotation) * (p - position); }
        public Vector3 InverseTransformVector(Vector3 v) { return Quaternion.Inverse(rotation) * v; }
        public Vector3 TransformVector(Vector3 v) { return rotation * v; }
    }

    public struct Vector3
    {
        public float x, y, z;
        public Vector3(float x, float y, float z) { this.x = x; this.y = y; this.z = z; }
        public static Vector3 operator +(Vector3 a, Vector3 b) { return new Vector3(a.x + b.x, a.y + b.y, a.z + b.z); }
        public static Vector3 operator -(Vector3 a, Vector3 b) { return new Vector3(a.x - b.x, a.y - b.y, a.z - b.z); }
    }

    public struct Quaternion
    {
        public float x, y, z, w;
        public Quaternion(float x, float y, float z, float w) { this.x = x; this.y = y; this.z = z; this.w = w; }
        public static Quaternion identity { get { return new Quaternion(0, 0, 0, 1); } }
        public static Quaternion Inverse(Quaternion q) { return new Quaternion(-q.x, -q.y, -q.z, q.w); }

        public static Quaternion operator *(Quaternion a, Quaternion b)
        {
            return new Quaternion(a.w * b.x + a.x * b.w + a.y * b.z - a.z * b.y, a.w * b.y - a.x * b.z + a.y * b.w + a.z * b.x,
                                  a.w * b.z + a.x * b.y - a.y * b.x + a.z * b.w, a.w * b.w - a.x * b.x - a.y * b.y - a.z * b.z);
        }

        public static Vector3 operator *(Quaternion q, Vector3 v)
        {
            Quaternion r = q * new Quaternion(v.x, v.y, v.z, 0) * Inverse(q);
            return new Vector3(r.x, r.y, r.z);
        }
    }

    public class Renderer : Component { }

    /// <summary>Blendshape weights by index; StubWeights keeps what was set.</summary>
    public class SkinnedMeshRenderer : Renderer
    {
        public Mesh sharedMesh { get; set; }
        public Dictionary<int, float> StubWeights = new Dictionary<int, float>();
        public void SetBlendShapeWeight(int index, float value) { StubWeights[index] = value; }
        public float GetBlendShapeWeight(int index) { float w; return StubWeights.TryGetValue(index, out w) ? w : 0f; }
    }

    public class Mesh : Object
    {
        public List<string> StubBlendShapes = new List<string>();
        public int blendShapeCount { get { return StubBlendShapes.Count; } }
        public string GetBlendShapeName(int shapeIndex) { return StubBlendShapes[shapeIndex]; }
        public int GetBlendShapeIndex(string blendShapeName) { return StubBlendShapes.IndexOf(blendShapeName); }
    }

    public class Animator : Behaviour
    {
        public Dictionary<HumanBodyBones, Transform> StubBones = new Dictionary<HumanBodyBones, Transform>();
        public bool isHuman { get { return true; } }
        public Transform GetBoneTransform(HumanBodyBones humanBoneId)
        {
            Transform t;
            return StubBones.TryGetValue(humanBoneId, out t) ? t : null;
        }
    }

    // Same names and order as UnityEngine.HumanBodyBones (Enum.TryParse relies on the names).
    public enum HumanBodyBones
    {
        Hips, LeftUpperLeg, RightUpperLeg, LeftLowerLeg, RightLowerLeg, LeftFoot, RightFoot, Spine, Chest, Neck, Head,
        LeftShoulder, RightShoulder, LeftUpperArm, RightUpperArm, LeftLowerArm, RightLowerArm, LeftHand, RightHand,
        LeftToes, RightToes, LeftEye, RightEye, Jaw,
        LeftThumbProximal, LeftThumbIntermediate, LeftThumbDistal, LeftIndexProximal, LeftIndexIntermediate,
        LeftIndexDistal, LeftMiddleProximal, LeftMiddleIntermediate, LeftMiddleDistal, LeftRingProximal,
        LeftRingIntermediate, LeftRingDistal, LeftLittleProximal, LeftLittleIntermediate, LeftLittleDistal,
        RightThumbProximal, RightThumbIntermediate, RightThumbDistal, RightIndexProximal, RightIndexIntermediate,
        RightIndexDistal, RightMiddleProximal, RightMiddleIntermediate, RightMiddleDistal, RightRingProximal,
        RightRingIntermediate, RightRingDistal, RightLittleProximal, RightLittleIntermediate, RightLittleDistal,
        UpperChest, LastBone
    }

    [AttributeUsage(AttributeTargets.Field)]
    public class TooltipAttribute : Attribute { public TooltipAttribute(string tooltip) { } }
    [AttributeUsage(AttributeTargets.Field, AllowMultiple = true)]
    public class HeaderAttribute : Attribute { public HeaderAttribute(string header) { } }
}
