// Test driver: the server's messages, decoded by Protocol.Parse, driving AudioFlow (DimgestorAudioFlow.cs) the
// way DimgestorClient does (slow_down -> SlowDown, resume -> Resume + a pending audio_end), on a script.
// usage: mono FlowCheck.exe MAX_HELD_S SCRIPT   (lines: "message JSON" | "chunk ID SECONDS" | "end")
// Prints one JSON line per line of the script; tests/test_clients_unity.py checks them.
using System;
using System.Collections.Generic;
using System.Globalization;
using System.IO;
using System.Linq;
using System.Text;
using Dimgestor;

static class FlowCheck
{
    static string N(double v) { return v.ToString("R", CultureInfo.InvariantCulture); }

    static int Main(string[] args)
    {
        var flow = new AudioFlow(double.Parse(args[0], CultureInfo.InvariantCulture));
        foreach (var line in File.ReadAllLines(args[1], Encoding.UTF8))
        {
            var w = line.Split(new[] { ' ' }, 2);
            if (w[0].Length == 0) continue;
            var sent = new List<byte[]>();
            string type = "", code = "";
            double backlog = -1;
            bool endNow = false;
            if (w[0] == "message")
            {
                var m = Protocol.Parse(w[1]);
                type = m.Type;
                var e = m as ErrorMessage;
                if (e != null) { code = e.Code; if (e.IsSlowDown) flow.SlowDown(); }
                var r = m as Resume;
                if (r != null) { backlog = r.BacklogS; sent = flow.Resume(); endNow = flow.TakeEndPending(); }
            }
            else if (w[0] == "chunk")
            {
                var p = w[1].Split(' ');
                sent = flow.Offer(Encoding.UTF8.GetBytes(p[0]), double.Parse(p[1], CultureInfo.InvariantCulture));
            }
            else if (w[0] == "end") endNow = flow.End();
            Console.WriteLine("{\"event\":\"" + w[0] + "\",\"type\":\"" + type + "\",\"code\":\"" + code + "\",\"backlog_s\":" + N(backlog)
                + ",\"sent\":[" + string.Join(",", sent.Select(b => "\"" + Encoding.UTF8.GetString(b) + "\"")) + "],\"end_now\":"
                + (endNow ? "true" : "false") + ",\"paused\":" + (flow.Paused ? "true" : "false") + ",\"held_s\":" + N(flow.HeldS)
                + ",\"dropped_s\":" + N(flow.DroppedS) + ",\"dropped_chunks\":" + flow.DroppedChunks
                + ",\"pauses\":" + flow.Pauses + ",\"resumes\":" + flow.Resumes + "}");
        }
        return 0;
    }
}
