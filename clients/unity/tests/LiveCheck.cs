// Test driver: DimgestorClient against a live `streamer serve`, the way Unity runs it: OnEnable starts the
// ClientWebSocket task, LateUpdate runs at 60 Hz on the "main" thread and poses a stand-in avatar
// (StubAvatar.cs), and SendAudio/EndAudio stream the first SECONDS of a 16-bit WAV in real time from
// another thread (the client's own session), paused by the server's slow_down until its resume. The client asks for
// the ARKit face and drives a stand-in face mesh with four of its names. Prints a JSON summary for
// tests/test_clients_unity.py.
// usage: mono LiveCheck.exe URL WAV SECONDS
using System;
using System.Globalization;
using System.IO;
using System.Linq;
using System.Net.WebSockets;
using System.Reflection;
using System.Text;
using System.Threading;
using System.Threading.Tasks;
using Dimgestor;
using UnityEngine;

static class LiveCheck
{
    static Hello ReadHello(string url)
    {
        using (var ws = new ClientWebSocket())
        {
            ws.ConnectAsync(new Uri(url), CancellationToken.None).Wait();
            var buffer = new byte[1 << 20];
            int n = 0;
            while (true)
            {
                var r = ws.ReceiveAsync(new ArraySegment<byte>(buffer, n, buffer.Length - n), CancellationToken.None).Result;
                n += r.Count;
                if (r.EndOfMessage) break;
            }
            return (Hello)Protocol.Parse(Encoding.UTF8.GetString(buffer, 0, n));
        }
    }

    /// <summary>Mono 16-bit PCM WAV -> (samples, rate).</summary>
    static float[] ReadWav(string path, out int rate)
    {
        var b = File.ReadAllBytes(path);
        rate = 0;
        int channels = 1;
        for (int p = 12; p + 8 <= b.Length;)
        {
            string id = Encoding.ASCII.GetString(b, p, 4);
            int size = BitConverter.ToInt32(b, p + 4);
            if (id == "fmt ") { channels = BitConverter.ToInt16(b, p + 10); rate = BitConverter.ToInt32(b, p + 12); }
            if (id == "data")
            {
                int count = Math.Min(size, b.Length - p - 8) / 2 / channels;
                var x = new float[count];
                for (int i = 0; i < count; i++) x[i] = BitConverter.ToInt16(b, p + 8 + 2 * i * channels) / 32768f;
                return x;
            }
            p += 8 + size + (size & 1);
        }
        throw new InvalidDataException(path + ": no data chunk");
    }

    static int Main(string[] args)
    {
        string url = args[0];
        int rate;
        float[] audio = ReadWav(args[1], out rate);
        double seconds = double.Parse(args[2], CultureInfo.InvariantCulture);
        var serverHello = ReadHello(url);
        var avatar = new StubAvatar(serverHello, 20f, 3);
        var faceMesh = new SkinnedMeshRenderer { sharedMesh = new Mesh { StubBlendShapes = { "jawOpen", "eyeBlinkLeft", "eyeBlinkRight", "mouthClose" } } };
        var client = new DimgestorClient { animator = avatar.Animator, url = url, binaryFrames = true, face = "arkit",
                                           faceMeshes = new[] { faceMesh } };
        var flags = BindingFlags.NonPublic | BindingFlags.Instance;
        typeof(DimgestorClient).GetMethod("OnEnable", flags).Invoke(client, null);
        var lateUpdate = typeof(DimgestorClient).GetMethod("LateUpdate", flags);

        Task sender = null;
        int ticks = 0, changed = 0, faceChanged = 0;
        var faceMax = new float[4];
        float[] facePrevious = null;
        double moved = 0;
        var bones = avatar.ByJoint.Values.ToArray();
        Vector3[] first = null, previous = null;
        var clock = System.Diagnostics.Stopwatch.StartNew();
        // A bound, not a measure: the loop leaves as soon as every frame came. On CI's two cores beside other work
        // a worker's hand-over and the resumed session took longer than 25 s once (38 frames of 120 by then).
        while (clock.Elapsed.TotalSeconds < seconds + 60)
        {
            if (sender == null && client.connectionState == "open")
            {
                sender = Task.Run(async () =>
                {
                    int chunk = rate / 50;  // 20 ms
                    var start = System.Diagnostics.Stopwatch.StartNew();
                    for (int i = 0; i < Math.Min(audio.Length, (int)(seconds * rate)); i += chunk)
                    {
                        var part = audio.Skip(i).Take(chunk).ToArray();
                        if (!await client.SendAudio(part, rate)) throw new IOException("SendAudio: not connected");
                        double due = (i + chunk) / (double)rate - start.Elapsed.TotalSeconds;  // real time, like a mic
                        if (due > 0) await Task.Delay(TimeSpan.FromSeconds(due));
                    }
                    await client.EndAudio();
                });
            }
            lateUpdate.Invoke(client, null);
            ticks++;
            var now = bones.Select(t => Quaternion.Inverse(avatar.Root.rotation) * (t.position - avatar.Root.position)).ToArray();
            if (first == null) first = now;
            if (previous != null && now.Zip(previous, (a, c) => Math.Abs(a.x - c.x) + Math.Abs(a.y - c.y) + Math.Abs(a.z - c.z)).Max() > 1e-7) changed++;
            moved = Math.Max(moved, now.Zip(first, (a, c) => Math.Abs(a.x - c.x) + Math.Abs(a.y - c.y) + Math.Abs(a.z - c.z)).Max());
            previous = now;
            var face = Enumerable.Range(0, 4).Select(faceMesh.GetBlendShapeWeight).ToArray();
            if (facePrevious != null && face.Zip(facePrevious, (a, c) => Math.Abs(a - c)).Max() > 1e-4) faceChanged++;
            for (int k = 0; k < 4; k++) faceMax[k] = Math.Max(faceMax[k], face[k]);
            facePrevious = face;
            if (sender != null && sender.IsCompleted && client.framesReceived >= (long)(seconds * 20) - 2 && changed > 0
                && clock.Elapsed.TotalSeconds > seconds + 2) break;
            Thread.Sleep(16);
        }
        typeof(DimgestorClient).GetMethod("OnDisable", flags).Invoke(client, null);
        string error = sender != null && sender.IsFaulted ? sender.Exception.InnerException.Message : client.lastError;
        var flow = (AudioFlow)typeof(DimgestorClient).GetField("flow", flags).GetValue(client);
        Console.WriteLine("{\"state\":\"" + client.connectionState + "\",\"frames\":" + client.framesReceived + ",\"ticks\":" + ticks
            + ",\"changed\":" + changed + ",\"moved\":" + moved.ToString("R", CultureInfo.InvariantCulture) + ",\"sent\":"
            + (sender != null && sender.Status == TaskStatus.RanToCompletion ? "true" : "false")
            + ",\"pauses\":" + flow.Pauses + ",\"resumes\":" + flow.Resumes + ",\"paused\":" + (client.audioPaused ? "true" : "false")
            + ",\"dropped_s\":" + flow.DroppedS.ToString("R", CultureInfo.InvariantCulture)
            + ",\"server_face\":" + (serverHello.Face != null ? "true" : "false") + ",\"face_weights_set\":" + faceMesh.StubWeights.Count
            + ",\"face_changed\":" + faceChanged + ",\"face_max\":[" + string.Join(",", faceMax.Select(w => w.ToString("R", CultureInfo.InvariantCulture))) + "]"
            + ",\"face_unmatched\":\"" + client.faceUnmatched + "\""
            + ",\"handovers\":" + client.handovers + ",\"resumed\":" + client.resumed + ",\"error\":\""
            + (error ?? "").Replace("\\", "\\\\").Replace("\"", "\\\"") + "\"}");
        return 0;
    }
}
