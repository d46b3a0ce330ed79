// Unity client for dimgestor (protocol v1 revision 7): receives gesture frames over a WebSocket and drives a Humanoid
// avatar through Animator.GetBoneTransform, and its face's blendshapes (DimgestorFace.cs). No third-party package:
// System.Net.WebSockets.ClientWebSocket (UniVRM only with the DIMGESTOR_UNIVRM define).
//
// Retargeting: the server's skeleton and the avatar have different bone axes, so local rotations cannot
// be copied. For each mapped bone we take the source joint's global rotation relative to the source rest
// pose (delta = G_frame * G_rest^-1, converted to Unity space) and apply it on top of the avatar's own
// rest: bone.rotation = avatarRoot.rotation * delta * A * boneRestRelativeToRoot. The avatar's bind pose may
// differ from the skeleton's rest (an A-pose avatar, a T-pose skeleton): A (DimgestorRestAlignment.cs) first
// turns the avatar's rest bone onto the skeleton's, so any bind pose works.
using System;
using System.Collections.Generic;
using System.Net.WebSockets;
using System.Text;
using System.Threading;
using System.Threading.Tasks;
using UnityEngine;

namespace Dimgestor
{
    public class DimgestorClient : MonoBehaviour
    {
        [Tooltip("Server WebSocket URL, e.g. ws://127.0.0.1:8765/")]
        public string url = "ws://127.0.0.1:8765/";
        [Tooltip("Access token when the server runs with --token (added as ?token=)")]
        public string token = "";
        [Tooltip("Receive DGF1 binary frames (smaller, faster to decode) instead of JSON")]
        public bool binaryFrames = true;
        [Tooltip("Humanoid avatar to drive; defaults to the Animator on this GameObject")]
        public Animator animator;
        [Tooltip("Move the hips with the source root (scaled to the avatar's hip height)")]
        public bool applyRootPosition = true;
        [Tooltip("Audio held while the server has us paused (slow_down until resume); beyond it the oldest is dropped")]
        public float maxHeldAudioS = (float)AudioFlow.DefaultMaxHeldS;

        [Header("Face")]
        [Tooltip("Face name set to ask for: vrm0 (VRM 0.x presets A I U E O Blink...), vrm1, arkit (52 ARKit names), oculus (visemes); none: no face")]
        public string face = "vrm0";
        [Tooltip("A speaker of a model trained on several (the server's hello lists them): our sessions play that speaker's style; empty: the server's default")]
        public string speaker = "";
        [Tooltip("Meshes whose blendshapes the face drives (face name -> blendshape of the same name, or through Face Name Map)")]
        public SkinnedMeshRenderer[] faceMeshes = new SkinnedMeshRenderer[0];
        [Tooltip("Face name -> your blendshape's name, where they differ (e.g. A -> Fcl_MTH_A)")]
        public FaceName[] faceNameMap = new FaceName[0];
        [Tooltip("Blendshape weight for a face weight of 1 (Unity blendshapes run 0..100)")]
        public float blendShapeScale = 100f;
#if DIMGESTOR_UNIVRM
        [Tooltip("VRM 0.x model's proxy; defaults to the one on this GameObject")]
        public VRM.VRMBlendShapeProxy vrmBlendShapeProxy;
#endif

        [Header("Read only")]
        public string connectionState = "idle";
        public long framesReceived;
        public float latencyMs;
        public long droppedFrames;
        public string lastError = "";
        public bool audioPaused;                  // between the server's slow_down and its resume
        public float heldAudioS;                  // audio waiting for resume
        public float droppedAudioS;               // held beyond maxHeldAudioS: dropped (oldest first)
        public int handovers;                     // goaways while we had our own session (the worker stopped)
        public int resumed;                       // sessions resumed on another worker after a goaway
        public string faceUnmatched = "";         // face names that drive no blendshape (check faceNameMap)
        public bool faceWithheld;                 // this session was admitted without its face (face_withheld: the
                                                  // server is at capacity for faces): the face rests until one comes
        public string faceNotice = "";            // why (the server's words); a notice, not an error

        class Binding { public Transform bone; public string name; public int joint; public Quaternion rest, align; }

        readonly object gate = new object();      // guards the fields the socket thread hands over
        Hello pendingHello;
        readonly FramePlayout playout = new FramePlayout();  // frames come in bursts: show each at its pts
        readonly System.Diagnostics.Stopwatch clock = System.Diagnostics.Stopwatch.StartNew();
        Frame shown;
        readonly FaceApplier faceApplier = new FaceApplier();
        readonly Dictionary<string, double> restingFace = new Dictionary<string, double>();  // the names shown, at 0
        bool faceAtRest = true;                   // set to restingFace since the last frame with a face
        Hello hello;
        Quat[] sourceRestGlobal;
        readonly List<Binding> bindings = new List<Binding>();
        Transform hips;
        Vector3 hipsRest;
        Vec3? rootReference;                      // first root of a stream: root motion is relative to it
        bool keepStream;                          // the next hello is a resumed session's: its stream goes on
        long lastIndex = -1;
        float hipsScale = 1f;

        CancellationTokenSource cts;
        ClientWebSocket socket;
        readonly SemaphoreSlim sendLock = new SemaphoreSlim(1, 1);  // ClientWebSocket allows one send at a time
        int audioFormatKey;                       // rate * 16 + channels declared in our last hello (0: none yet)
        readonly AudioFlow flow = new AudioFlow();  // slow_down / resume (protocol revision 2)

        // Hand-over (revision 3): a stopping worker sends goaway with a token; we connect again (a balancer picks
        // another worker), resume_session, and re-send our audio from the sample the saved state covers: so the
        // last ResendS seconds we sent are kept, and SendAudio holds its chunks meanwhile (as at slow_down).
        const double ResendS = 15, ResumeWithinS = 10;
        class SentChunk { public long First; public byte[] Bytes; public int Samples; }
        readonly List<SentChunk> sent = new List<SentChunk>();
        long sentSamples;
        int audioRate, audioChannels = 1;
        string resumeToken;                       // from a goaway until session_resumed
        DateTime resumeSince;

        void OnEnable()
        {
            if (animator == null) animator = GetComponent<Animator>();
#if DIMGESTOR_UNIVRM
            if (vrmBlendShapeProxy == null) vrmBlendShapeProxy = GetComponent<VRM.VRMBlendShapeProxy>();
#endif
            cts = new CancellationTokenSource();
            var ct = cts.Token;
            Task.Run(() => RunAsync(ct));
        }

        void OnDisable()
        {
            if (cts != null) cts.Cancel();
            var s = socket;
            if (s != null) s.Abort();
        }

        async Task RunAsync(CancellationToken ct)
        {
            var uri = new Uri(string.IsNullOrEmpty(token) ? url : url + (url.Contains("?") ? "&" : "?") + "token=" + Uri.EscapeDataString(token));
            while (!ct.IsCancellationRequested)
            {
                try
                {
                    using (var ws = new ClientWebSocket())
                    {
                        connectionState = "connecting";
                        await ws.ConnectAsync(uri, ct).ConfigureAwait(false);
                        socket = ws;
                        if (resumeToken != null && (DateTime.UtcNow - resumeSince).TotalSeconds > ResumeWithinS)
                        {
                            resumeToken = null;  // could not resume in time: a fresh session (what was held is dropped)
                            lastError = "could not resume our session after a goaway: a fresh one starts";
                        }
                        if (resumeToken != null)  // our session goes on here: its format, then the token
                        {
                            connectionState = "resuming";
                            audioFormatKey = audioRate * 16 + audioChannels;
                            await SendText(Protocol.ClientHello(binaryFrames, audioRate, "float32", audioChannels, face, speaker), ct).ConfigureAwait(false);
                            await SendText(Protocol.ResumeSession(resumeToken), ct).ConfigureAwait(false);
                        }
                        else
                        {
                            audioFormatKey = 0;
                            flow.Reset();
                            audioPaused = false;
                            lock (sent) { sent.Clear(); sentSamples = 0; }
                            connectionState = "open";
                            await SendText(Protocol.ClientHello(binaryFrames, face: face, speaker: speaker), ct).ConfigureAwait(false);
                        }
                        await ReceiveLoop(ws, ct).ConfigureAwait(false);
                    }
                }
                catch (OperationCanceledException) { break; }
                catch (Exception e)  // refused (e.g. 401: wrong token), dropped, bad data
                {
                    if (resumeToken == null) lastError = e.Message;  // (after a goaway the worker closes: expected)
                }
                socket = null;
                connectionState = resumeToken != null ? "moving" : "closed, retrying";
                try { await Task.Delay(resumeToken != null ? 100 : 2000, ct).ConfigureAwait(false); }
                catch (OperationCanceledException) { break; }
            }
            connectionState = "stopped";
        }

        async Task ReceiveLoop(ClientWebSocket ws, CancellationToken ct)
        {
            var buffer = new byte[64 * 1024];
            var message = new System.IO.MemoryStream();
            var decoder = new MessageDecoder();  // this connection's binary layout: its hello's, then each `channels` message's
            while (ws.State == WebSocketState.Open && !ct.IsCancellationRequested)
            {
                var r = await ws.ReceiveAsync(new ArraySegment<byte>(buffer), ct).ConfigureAwait(false);
                if (r.MessageType == WebSocketMessageType.Close) return;
                message.Write(buffer, 0, r.Count);
                if (!r.EndOfMessage) continue;
                var data = message.ToArray();
                message.SetLength(0);
                try
                {
                    if (r.MessageType == WebSocketMessageType.Binary) Handle(decoder.Binary(data, 0, data.Length));
                    else Handle(decoder.Text(Encoding.UTF8.GetString(data)));
                }
                catch (ProtocolException e) { lastError = e.Message; }  // one bad message does not end the stream
            }
        }

        void Handle(Message m)
        {
            var f = m as Frame;
            if (f != null)
            {
                lock (gate) playout.Push(f, clock.Elapsed.TotalSeconds);
                framesReceived++;
                if (f.Face.Count > 0) faceWithheld = false;  // the face is back (a later session)
                return;
            }
            var h = m as Hello;
            if (h != null)
            {
                lock (gate)
                {
                    pendingHello = h;
                    keepStream = resumeToken != null;  // a resumed session: its frames and root go on
                    if (!keepStream) playout.Reset();
                    // Buffer one inference window (the burst length) plus some network jitter.
                    playout.DelayS = (h.WindowMs > 0 ? h.WindowMs / 1000.0 : 0.25) + 0.06;
                }
                return;
            }
            var s = m as Status;
            if (s != null) { latencyMs = (float)s.LatencyMs; droppedFrames = s.Dropped; return; }
            var g = m as GoAway;
            if (g != null && audioFormatKey != 0 && !string.IsNullOrEmpty(g.Token))  // our session moves: hold our audio
            {
                resumeSince = DateTime.UtcNow;
                resumeToken = g.Token;
                handovers++;
                flow.SlowDown();
                audioPaused = true;
                return;
            }
            var r = m as SessionResumed;
            if (r != null && resumeToken != null)
            {
                resumeToken = null;
                resumed++;
                connectionState = "open";
                audioPaused = false;
                SendHeld(r.Samples);  // (not awaited: the receive loop goes on)
                return;
            }
            var e = m as ErrorMessage;
            if (e != null && resumeToken != null && (e.Code == "busy" || e.Code == "resume_failed"))
            {
                if (e.Code == "resume_failed") { resumeToken = null; lastError = e.Code + ": " + e.Text; audioPaused = false; SendHeld(); }
                else { var sock = socket; if (sock != null) sock.Abort(); }  // a worker stopping too: another one (the token stays good)
                return;
            }
            if (e != null && e.IsSlowDown) { flow.SlowDown(); audioPaused = true; return; }  // a notice, not an error
            if (e != null && e.Code == "face_withheld") { faceWithheld = true; faceNotice = e.Text; return; }  // a notice too
            if (e != null) { lastError = e.Code + ": " + e.Text; return; }
            if (m is Resume) { audioPaused = false; SendHeld(); }  // (not awaited: the receive loop goes on)
        }

        /// <summary>After `resume`: what was held while paused goes first, in order, then a pending audio_end. After
        /// `session_resumed` (resendFrom >= 0): first our audio again from that sample on.</summary>
        async void SendHeld(long resendFrom = -1)  // (async void: every exception is caught inside)
        {
            var ws = socket;
            if (ws == null || cts == null) return;
            var ct = cts.Token;
            try
            {
                await sendLock.WaitAsync(ct).ConfigureAwait(false);
                try
                {
                    if (resendFrom >= 0)
                    {
                        List<SentChunk> again;
                        lock (sent) again = sent.FindAll(c => c.First + c.Samples > resendFrom);
                        foreach (var c in again)
                        {
                            int skip = (int)Math.Max(0, resendFrom - c.First) * 4 * audioChannels;
                            var bytes = skip == 0 ? c.Bytes : new ArraySegment<byte>(c.Bytes, skip, c.Bytes.Length - skip).ToArray();
                            await Send(ws, bytes, WebSocketMessageType.Binary, ct).ConfigureAwait(false);
                        }
                    }
                    foreach (var chunk in flow.Resume())
                    {
                        await Send(ws, chunk, WebSocketMessageType.Binary, ct).ConfigureAwait(false);
                        KeepSent(chunk);
                    }
                    if (flow.TakeEndPending()) await Send(ws, Encoding.UTF8.GetBytes(AudioEnd), WebSocketMessageType.Text, ct).ConfigureAwait(false);
                    heldAudioS = (float)flow.HeldS;
                }
                finally { sendLock.Release(); }
            }
            catch (Exception x) { lastError = x.Message; }  // the connection went meanwhile: the receive loop reconnects
        }

        // After the Animator, so an Animator Controller (if any) does not overwrite the gestures.
        void LateUpdate()
        {
            Hello h; Frame f;
            lock (gate) { h = pendingHello; pendingHello = null; f = playout.Sample(clock.Elapsed.TotalSeconds); }
            if (h != null) Bind(h);
            if (f != null && f != shown && hello != null) { Apply(f); ApplyFace(f); shown = f; }
        }

        // The inspector changed a field (e.g. the meshes or the name map): work the face's blendshapes out again.
        void OnValidate() { faceApplier.Reset(); }

        /// <summary>The face of the frame shown (interpolated with its pose) on the meshes and the VRM. A frame without
        /// a face (withheld at capacity, or none asked) sets every name shown before to 0, once.</summary>
        void ApplyFace(Frame f)
        {
            var face = f.Face;
            if (face.Count == 0)
            {
                if (faceAtRest) return;
                faceAtRest = true;
                face = restingFace;
            }
            else
            {
                faceAtRest = false;
                foreach (var kv in face) restingFace[kv.Key] = 0.0;  // (no allocation once every name was seen)
            }
            faceApplier.Scale = blendShapeScale;
            faceApplier.Apply(face, faceMeshes, faceNameMap);
#if DIMGESTOR_UNIVRM
            FaceApplier.ApplyVrm(face, vrmBlendShapeProxy, faceNameMap);
            if (vrmBlendShapeProxy != null) { faceUnmatched = ""; return; }  // the proxy takes every name it has a clip for
#endif
            faceUnmatched = faceApplier.Unmatched;
        }

        void Bind(Hello h)
        {
            if (animator == null || !animator.isHuman) { lastError = "needs a Humanoid Animator"; return; }
            if (hello != null) RestoreRest();  // a reconnect: measure the avatar's rest, not the last pose
            bindings.Clear();
            faceApplier.Reset();
            hello = h;
            sourceRestGlobal = Protocol.GlobalRotations(h.Skeleton, h.Skeleton.RestRotations);
            Quaternion rootInv = Quaternion.Inverse(animator.transform.rotation);
            foreach (var kv in h.Humanoid)
            {
                HumanBodyBones id;
                if (!Enum.TryParse(kv.Key, out id) || id == HumanBodyBones.LastBone) continue;
                Transform bone = animator.GetBoneTransform(id);  // null where the avatar lacks the bone
                int joint = h.Skeleton.IndexOf(kv.Value);
                if (bone == null || joint < 0) continue;
                bindings.Add(new Binding { bone = bone, name = id.ToString(), joint = joint, rest = rootInv * bone.rotation });
            }
            bindings.Sort((a, b) => a.joint.CompareTo(b.joint));  // parents before children
            // The bind pose need not be the skeleton's rest (an A-pose): each rest bone is turned onto the skeleton's first.
            Quat[] align = RestAlignment.Compute(h.Skeleton, bindings.ConvertAll(b => b.name).ToArray(),
                bindings.ConvertAll(b => b.joint).ToArray(),
                bindings.ConvertAll(b => { Vector3 p = rootInv * b.bone.position; return new Vec3(p.x, p.y, p.z); }).ToArray());
            for (int i = 0; i < bindings.Count; i++) bindings[i].align = ToQuaternion(align[i]);
            hips = animator.GetBoneTransform(HumanBodyBones.Hips);
            if (hips != null) hipsRest = hips.localPosition;
            if (!keepStream) { rootReference = null; lastIndex = -1; }
            keepStream = false;
        }

        void RestoreRest()
        {
            Quaternion root = animator.transform.rotation;
            foreach (var b in bindings) b.bone.rotation = root * b.rest;
            if (hips != null) hips.localPosition = hipsRest;
        }

        void Apply(Frame f)
        {
            var sk = hello.Skeleton;
            if (f.Rotations.Length != sk.Joints.Length) { lastError = "frame has " + f.Rotations.Length + " rotations for " + sk.Joints.Length + " joints"; return; }
            Quat[] g = Protocol.GlobalRotations(sk, f.Rotations);
            Quaternion root = animator.transform.rotation;
            foreach (var b in bindings)
            {
                Quat d = Protocol.ToUnityRotation(g[b.joint] * sourceRestGlobal[b.joint].Conjugate());
                b.bone.rotation = root * ToQuaternion(d) * b.align * b.rest;
            }
            if (f.Index < lastIndex) rootReference = null;  // a new stream (own audio session, --loop)
            lastIndex = f.Index;
            if (applyRootPosition && hips != null)
            {
                if (rootReference == null)
                {
                    rootReference = f.Root;
                    double sourceHeight = Protocol.ToUnityPosition(f.Root, sk.UnitToMeters).Y;
                    float avatarHeight = (animator.transform.InverseTransformPoint(hips.position)).y;
                    hipsScale = sourceHeight > 0.1 && avatarHeight > 0.1f ? avatarHeight / (float)sourceHeight : 1f;
                }
                Vec3 d = Protocol.ToUnityPosition(f.Root - rootReference.Value, sk.UnitToMeters) * hipsScale;
                Vector3 local = hipsRest + (hips.parent != null
                    ? hips.parent.InverseTransformVector(animator.transform.TransformVector(new Vector3((float)d.X, (float)d.Y, (float)d.Z)))
                    : new Vector3((float)d.X, (float)d.Y, (float)d.Z));
                hips.localPosition = local;
            }
        }

        static Quaternion ToQuaternion(Quat q) { return new Quaternion((float)q.X, (float)q.Y, (float)q.Z, (float)q.W); }

        // ---- optional: send your own audio (e.g. from Microphone or OnAudioFilterRead) for an own session

        // Flow control (protocol revision 2): after the server's slow_down, chunks are held (at most maxHeldAudioS,
        // the oldest dropped beyond it and counted in droppedAudioS) and go out at its resume, in order.

        const string AudioEnd = "{\"type\":\"audio_end\"}";

        /// <summary>Send float samples (interleaved if channels == 2): now, or held while the server has us paused.
        /// Thread-safe; returns false when not connected.</summary>
        public async Task<bool> SendAudio(float[] samples, int sampleRate, int channels = 1)
        {
            var ws = socket;
            bool moving = resumeToken != null;  // our session is moving to another worker: held meanwhile
            if (!moving && (ws == null || ws.State != WebSocketState.Open) || cts == null) return false;
            var ct = cts.Token;
            var bytes = Protocol.EncodeFloat32(samples, 0, samples.Length);
            await sendLock.WaitAsync(ct).ConfigureAwait(false);
            try
            {
                if (!moving && sampleRate * 16 + channels != audioFormatKey)  // declare the format before the first chunk
                {
                    flow.DropHeld();  // (held audio of another format cannot follow the new hello)
                    await Send(ws, Encoding.UTF8.GetBytes(Protocol.ClientHello(binaryFrames, sampleRate, "float32", channels, face, speaker)),
                               WebSocketMessageType.Text, ct).ConfigureAwait(false);
                    audioFormatKey = sampleRate * 16 + channels;
                    audioRate = sampleRate;
                    audioChannels = channels;
                    lock (sent) { sent.Clear(); sentSamples = 0; }
                }
                flow.MaxHeldS = maxHeldAudioS;
                foreach (var chunk in flow.Offer(bytes, samples.Length / (double)(channels * sampleRate)))
                {
                    await Send(ws, chunk, WebSocketMessageType.Binary, ct).ConfigureAwait(false);
                    KeepSent(chunk);
                }
                heldAudioS = (float)flow.HeldS;
                if (flow.DroppedS > 0 && droppedAudioS == 0)
                    Debug.LogWarning("dimgestor: paused by the server for over " + maxHeldAudioS + " s: dropping the oldest audio (droppedAudioS)");
                droppedAudioS = (float)flow.DroppedS;
            }
            finally { sendLock.Release(); }
            return true;
        }

        /// <summary>No more audio: the server finishes the session and sends "end" (after `resume` if paused).</summary>
        public async Task EndAudio()
        {
            var ws = socket;
            if (resumeToken == null && (ws == null || ws.State != WebSocketState.Open) || cts == null) return;
            var ct = cts.Token;
            await sendLock.WaitAsync(ct).ConfigureAwait(false);
            try { if (flow.End()) await Send(ws, Encoding.UTF8.GetBytes(AudioEnd), WebSocketMessageType.Text, ct).ConfigureAwait(false); }
            finally { sendLock.Release(); }
        }

        /// <summary>A chunk of our audio went out: kept (the last ResendS seconds) to be sent again after a goaway.</summary>
        void KeepSent(byte[] chunk)
        {
            int n = chunk.Length / (4 * audioChannels);
            lock (sent)
            {
                sent.Add(new SentChunk { First = sentSamples, Bytes = chunk, Samples = n });
                sentSamples += n;
                while (sent.Count > 1 && sentSamples - sent[0].First - sent[0].Samples > ResendS * audioRate) sent.RemoveAt(0);
            }
        }

        async Task SendText(string text, CancellationToken ct)
        {
            var ws = socket;
            if (ws == null || ws.State != WebSocketState.Open) return;
            await sendLock.WaitAsync(ct).ConfigureAwait(false);
            try { await Send(ws, Encoding.UTF8.GetBytes(text), WebSocketMessageType.Text, ct).ConfigureAwait(false); }
            finally { sendLock.Release(); }
        }

        // ClientWebSocket allows one send at a time: callers hold sendLock.
        static Task Send(ClientWebSocket ws, byte[] bytes, WebSocketMessageType type, CancellationToken ct)
        {
            return ws.SendAsync(new ArraySegment<byte>(bytes), type, true, ct);
        }
    }
}
