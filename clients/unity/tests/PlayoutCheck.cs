// Test driver: FramePlayout (DimgestorPlayout.cs) on recorded frames and a schedule of arrivals and samples.
// usage: mono PlayoutCheck.exe FOLDER SCHEDULE   (schedule lines: "push K T" | "sample T" | "delay S")
// Prints one JSON line per sample; tests/test_clients_playout.py compares the three clients' outputs.
using System;
using System.Collections.Generic;
using System.Globalization;
using System.IO;
using System.Linq;
using System.Text;
using Dimgestor;

static class PlayoutCheck
{
    static string N(double v) { return v.ToString("R", CultureInfo.InvariantCulture); }

    static int Main(string[] args)
    {
        var frames = new List<Frame>();
        foreach (var path in Directory.GetFiles(args[0]).OrderBy(p => p, StringComparer.Ordinal))
        {
            if (path.EndsWith(".bin")) { var b = File.ReadAllBytes(path); frames.Add(Protocol.DecodeBinaryFrame(b, 0, b.Length)); }
            else if (path.EndsWith(".json")) { var f = Protocol.Parse(File.ReadAllText(path, Encoding.UTF8)) as Frame; if (f != null) frames.Add(f); }
        }
        var playout = new FramePlayout();
        foreach (var line in File.ReadAllLines(args[1]))
        {
            var w = line.Split(new[] { ' ', '\t' }, StringSplitOptions.RemoveEmptyEntries);
            if (w.Length == 0) continue;
            Func<int, double> num = i => double.Parse(w[i], CultureInfo.InvariantCulture);
            if (w[0] == "delay") playout.DelayS = num(1);
            else if (w[0] == "push") playout.Push(frames[int.Parse(w[1], CultureInfo.InvariantCulture)], num(2));
            else if (w[0] == "sample")
            {
                Frame s = playout.Sample(num(1));
                if (s == null) { Console.WriteLine("null"); continue; }
                Console.WriteLine("{\"index\":" + s.Index + ",\"pts\":" + N(s.Pts) + ",\"root\":[" + N(s.Root.X) + "," + N(s.Root.Y) + ","
                    + N(s.Root.Z) + "],\"rotations\":[" + string.Join(",", s.Rotations.Select(q => "[" + N(q.W) + "," + N(q.X) + ","
                    + N(q.Y) + "," + N(q.Z) + "]")) + "]}");
            }
        }
        Console.Error.WriteLine("reanchors " + playout.Reanchors);
        return 0;
    }
}
