// Flow control of the audio a client sends (protocol v1 revision 2, docs/protocol.md "Audio"), in plain C#:
// no Unity and no socket, so it is tested outside Unity (clients/unity/tests/FlowCheck.cs).
//
// Between a `slow_down` error (a notice: the server has 30 s of our audio queued) and its `resume`, the server
// wants no more audio. Chunks offered meanwhile are held, in order, at most MaxHeldS seconds of them: a live
// microphone wants now, not what was said long ago, so beyond the bound the oldest are dropped and counted
// (DroppedS). At `resume` the held chunks go out first; an audio_end asked for while paused goes after them.
using System.Collections.Generic;

namespace Dimgestor
{
    public class AudioFlow
    {
        public const double DefaultMaxHeldS = 10.0;

        readonly object gate = new object();  // Offer (any thread) and the receive loop's SlowDown/Resume
        readonly Queue<KeyValuePair<byte[], double>> held = new Queue<KeyValuePair<byte[], double>>();
        double heldS;

        public double MaxHeldS;
        public bool Paused { get; private set; }
        public bool EndPending { get; private set; }  // audio_end asked for while paused: send it after Resume's chunks
        public double DroppedS { get; private set; }
        public long DroppedChunks { get; private set; }
        public long Pauses { get; private set; }
        public long Resumes { get; private set; }
        public double HeldS { get { lock (gate) return heldS; } }

        public AudioFlow(double maxHeldS = DefaultMaxHeldS) { MaxHeldS = maxHeldS; }

        /// <summary>A chunk of `seconds` of audio to send: the chunks that may go now, in order (none while paused).</summary>
        public List<byte[]> Offer(byte[] chunk, double seconds)
        {
            lock (gate)
            {
                held.Enqueue(new KeyValuePair<byte[], double>(chunk, seconds));
                heldS += seconds;
                while (heldS > MaxHeldS && held.Count > 1)
                {
                    var old = held.Dequeue();
                    heldS -= old.Value;
                    DroppedS += old.Value;
                    DroppedChunks++;
                }
                return Paused ? new List<byte[]>() : TakeHeld();
            }
        }

        /// <summary>The server said `slow_down`: hold what comes until `resume`.</summary>
        public void SlowDown()
        {
            lock (gate) { if (!Paused) Pauses++; Paused = true; }
        }

        /// <summary>The server said `resume`: the held chunks, to send now (then audio_end if EndPending).</summary>
        public List<byte[]> Resume()
        {
            lock (gate) { if (Paused) Resumes++; Paused = false; return TakeHeld(); }
        }

        /// <summary>No more audio: true if audio_end may go now; false if paused (it goes after Resume's chunks).</summary>
        public bool End()
        {
            lock (gate) { EndPending = Paused; return !Paused; }
        }

        /// <summary>Whether an audio_end was waiting for `resume`; clears it.</summary>
        public bool TakeEndPending()
        {
            lock (gate) { bool e = EndPending; EndPending = false; return e; }
        }

        /// <summary>The held chunks are discarded, counted as dropped (their audio format is being replaced).</summary>
        public void DropHeld()
        {
            lock (gate) { foreach (var kv in held) { DroppedS += kv.Value; DroppedChunks++; } held.Clear(); heldS = 0; }
        }

        /// <summary>A new connection: nothing paused or held (what was held belonged to the old session).</summary>
        public void Reset()
        {
            lock (gate) { Paused = false; EndPending = false; held.Clear(); heldS = 0; }
        }

        List<byte[]> TakeHeld()
        {
            var out_ = new List<byte[]>(held.Count);
            foreach (var kv in held) out_.Add(kv.Key);
            held.Clear();
            heldS = 0;
            return out_;
        }
    }
}
