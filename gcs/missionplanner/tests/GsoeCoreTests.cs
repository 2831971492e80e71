// Console tests of the GSOE core (GsoeNav.GsoeDecoder), run with Mono:
//
//   mono GsoeCoreTests.exe                      unit tests on packets made here with the generated MAVLink library
//   mono GsoeCoreTests.exe FRAMES.tlog SCRIPT   also replays the companion's bytes against a script of expectations
//
// FRAMES.tlog: Mission Planner's telemetry-log layout, each frame an 8-byte big-endian receive time (microseconds)
// followed by one MAVLink packet. SCRIPT: one step per line (written by tests/test_missionplanner_plugin.py):
//   feed N                      hand the next N frames to the decoder (now = each frame's time)
//   check T                     Check(T): warnings due to time alone (now = T)
//   expect FIELD = TEXT         the snapshot's field (GsoeDisplayState.ToFields) equals TEXT (may be empty)
//   expect FIELD ~ VALUE TOL    ... is a number within TOL of VALUE
//   warnings N                  exactly N warnings were raised since the last `warnings` step (then forgotten)
//   warning TEXT                one of those warnings contains TEXT
// Every unit test and every expect/warnings/warning step counts as one test. The last line printed is
// "N passed, N failed"; the exit code is 0 only when nothing failed (and, with a tlog, every frame parsed).

using System;
using System.Collections.Generic;
using System.Globalization;
using System.IO;
using System.Threading;
using GsoeNav;

public static class GsoeCoreTests
{
    static int _passed, _failed;

    static void Check(bool ok, string what)
    {
        if (ok)
            _passed++;
        else
        {
            _failed++;
            Console.WriteLine("FAIL: " + what);
        }
    }

    static void Near(double got, double want, double tol, string what)
    {
        Check(Math.Abs(got - want) <= tol, what + ": got " + got.ToString("R", CultureInfo.InvariantCulture)
                                            + ", want " + want.ToString("R", CultureInfo.InvariantCulture));
    }

    // ------------------------------------------------------------------ packets made here
    static readonly MAVLink.MavlinkParse Parser = new MAVLink.MavlinkParse();

    /// <summary>`data` packed as MAVLink 2 by (sysid, compid), then parsed back as a ground station receives it.</summary>
    static MAVLink.MAVLinkMessage Received(MAVLink.MAVLINK_MSG_ID id, object data, byte sysid, byte compid)
    {
        byte[] bytes = Parser.GenerateMAVLinkPacket20(id, data, false, sysid, compid);
        var msg = Parser.ReadPacket(new MemoryStream(bytes));
        if (msg == null)
            throw new InvalidDataException("packet did not parse back: " + id);
        return msg;
    }

    static byte[] Chars(string s, int size)
    {
        var b = new byte[size];
        var src = System.Text.Encoding.ASCII.GetBytes(s);
        Array.Copy(src, b, Math.Min(size, src.Length));
        return b;
    }

    static MAVLink.MAVLinkMessage Named(string name, float value, byte compid)
    {
        var m = new MAVLink.mavlink_named_value_float_t();
        m.name = Chars(name, 10);
        m.value = value;
        return Received(MAVLink.MAVLINK_MSG_ID.NAMED_VALUE_FLOAT, m, 1, compid);
    }

    static MAVLink.MAVLinkMessage Wind(float direction_deg, float speed_m_s, byte compid)
    {
        var m = new MAVLink.mavlink_wind_t();
        m.direction = direction_deg;
        m.speed = speed_m_s;
        return Received(MAVLink.MAVLINK_MSG_ID.WIND, m, 1, compid);
    }

    static MAVLink.MAVLinkMessage Text(string text, byte compid)
    {
        var m = new MAVLink.mavlink_statustext_t();
        m.severity = 4;
        m.text = Chars(text, 50);
        return Received(MAVLink.MAVLINK_MSG_ID.STATUSTEXT, m, 1, compid);
    }

    const byte Companion = GsoeDecoder.CompanionComponentId;
    const byte Autopilot = 1;

    static void UnitTests()
    {
        // a 10-character name fills the field: no NUL to end it
        var d = new GsoeDecoder();
        d.Handle(Named("GSOE_VALID", 1f, Companion), 0.0);
        Check(d.Snapshot(0.0).Validity == GsoeValidity.Valid, "GSOE_VALID (10 chars, no NUL) read as valid");

        // the autopilot's own WIND is not the companion's; source component 0 accepts any
        d = new GsoeDecoder();
        d.Handle(Wind(90f, 3f, Autopilot), 0.0);
        Check(double.IsNaN(d.Snapshot(0.0).WindSpeed_m_s), "the autopilot's WIND (component 1) is ignored");
        var any = new GsoeDecoder(0, 0, GsoeDecoder.DefaultStale_s);
        any.Handle(Wind(90f, 3f, Autopilot), 0.0);
        Near(any.Snapshot(0.0).WindSpeed_m_s, 3.0, 1e-6, "source component 0 accepts the autopilot's WIND");
        var otherSystem = new GsoeDecoder(2, Companion, GsoeDecoder.DefaultStale_s);
        otherSystem.Handle(Wind(90f, 3f, Companion), 0.0);
        Check(double.IsNaN(otherSystem.Snapshot(0.0).WindSpeed_m_s), "another vehicle's companion is ignored");

        // non-finite values change nothing; a negative direction wraps
        d = new GsoeDecoder();
        d.Handle(Wind(float.NaN, 3f, Companion), 0.0);
        d.Handle(Named("GSOE_DRIFT", float.PositiveInfinity, Companion), 0.0);
        var s = d.Snapshot(0.0);
        Check(double.IsNaN(s.WindSpeed_m_s) && double.IsNaN(s.Drift_deg), "NaN/inf values are ignored");
        d.Handle(Wind(-90f, 3f, Companion), 0.0);
        Near(d.Snapshot(0.0).WindFrom_deg, 270.0, 1e-9, "direction -90 deg wraps to 270");

        // warnings: invalid (reason from the STATUSTEXT, once), valid again, GNSS change, silence (once)
        d = new GsoeDecoder();
        Check(d.Handle(Named("GSOE_VALID", 1f, Companion), 0.0).Count == 0, "first status: no warning");
        Check(d.Handle(Named("GSOE_GNSS", 0f, Companion), 0.0).Count == 0, "first GNSS state: no warning");
        var w = d.Handle(Text("GSOE invalid: estimate invalid (stale)", Companion), 1.0);
        Check(w.Count == 1 && w[0].Contains("INVALID: estimate invalid (stale)"), "STATUSTEXT invalid warns with reason");
        Check(d.Handle(Named("GSOE_VALID", 0f, Companion), 1.1).Count == 0, "GSOE_VALID 0 after it: no second warning");
        w = d.Handle(Named("GSOE_VALID", 1f, Companion), 2.0);
        Check(w.Count == 1 && w[0] == "GSOE estimate valid again", "valid again");
        Check(d.Snapshot(2.0).InvalidReason == "", "the reason is cleared when valid");
        w = d.Handle(Named("GSOE_GNSS", 2f, Companion), 2.5);
        Check(w.Count == 1 && w[0] == "GSOE GNSS state GNSS_OK -> GNSS_DENIED", "GNSS state change");
        Check(d.Check(4.9).Count == 0, "not silent within stale_s");
        w = d.Check(5.5);
        Check(w.Count == 1 && w[0].Contains("silent") && d.Snapshot(5.5).Validity == GsoeValidity.Stale, "silent");
        Check(d.Check(9.0).Count == 0, "silence is said once");
        d.Handle(Named("GSOE_VALID", 1f, Companion), 9.5);
        Check(d.Snapshot(9.5).Validity == GsoeValidity.Valid, "status again: no longer stale");

        // other texts and other names do not count; STATUSTEXT from another component is not ours
        d = new GsoeDecoder();
        d.Handle(Text("PreArm: GPS not healthy", Companion), 0.0);
        d.Handle(Text("GSOE invalid: x", Autopilot), 0.0);
        d.Handle(Named("ALT_X", 1f, Companion), 0.0);
        Check(d.Snapshot(0.0).Counts.Count == 0 && d.Snapshot(0.0).LastStatusText == "", "foreign texts/names ignored");

        // the display does not follow the PC's locale (a comma decimal separator)
        var saved = Thread.CurrentThread.CurrentCulture;
        try
        {
            Thread.CurrentThread.CurrentCulture = new CultureInfo("de-DE");
            d = new GsoeDecoder();
            Check((8.5).ToString("0.0") == "8,5", "the test's culture writes a decimal comma");
            d.Handle(Wind(270f, 8.2f, Companion), 0.0);
            d.Handle(Named("GSOE_DRIFT", -3.5f, Companion), 0.0);
            s = d.Snapshot(0.0);
            Check(s.WindLine == "Wind 8.2+--- m/s from 270+--- deg", "wind line in invariant culture: " + s.WindLine);
            Check(s.DriftLine == "Drift -3.5 deg  ATA -- deg", "drift line in invariant culture: " + s.DriftLine);
        }
        finally
        {
            Thread.CurrentThread.CurrentCulture = saved;
        }
    }

    // ------------------------------------------------------------------ the companion's bytes
    struct Frame
    {
        public double T_s;
        public MAVLink.MAVLinkMessage Msg;
    }

    static List<Frame> ReadTlog(string path, out int unparsed)
    {
        var frames = new List<Frame>();
        unparsed = 0;
        var parser = new MAVLink.MavlinkParse();
        using (var f = File.OpenRead(path))
        {
            var stamp = new byte[8];
            while (f.Position < f.Length)
            {
                if (f.Read(stamp, 0, 8) != 8)
                {
                    unparsed++;
                    break;
                }
                ulong us = 0;
                for (int i = 0; i < 8; i++)
                    us = (us << 8) | stamp[i];
                var msg = parser.ReadPacket(f);
                if (msg == null)
                {
                    unparsed++;  // bad CRC or truncated: the dialects disagree
                    continue;
                }
                var fr = new Frame();
                fr.T_s = us / 1e6;
                fr.Msg = msg;
                frames.Add(fr);
            }
        }
        return frames;
    }

    static void Replay(string tlog, string script)
    {
        int unparsed;
        var frames = ReadTlog(tlog, out unparsed);
        Check(unparsed == 0, "every frame of " + tlog + " parses (CRC and length), " + unparsed + " did not");
        var d = new GsoeDecoder();
        var pending = new List<string>();
        int next = 0;
        double now = 0.0;
        int lineNo = 0;
        foreach (var raw in File.ReadAllLines(script))
        {
            lineNo++;
            string line = raw.Trim();
            if (line.Length == 0 || line.StartsWith("#"))
                continue;
            string where = script + ":" + lineNo + " (" + line + ")";
            string[] p = line.Split(new[] { ' ' }, 2);
            string rest = p.Length > 1 ? p[1] : "";
            switch (p[0])
            {
                case "feed":
                {
                    int n = int.Parse(rest, CultureInfo.InvariantCulture);
                    for (int i = 0; i < n && next < frames.Count; i++, next++)
                    {
                        now = frames[next].T_s;
                        pending.AddRange(d.Handle(frames[next].Msg, now));
                    }
                    break;
                }
                case "check":
                    now = double.Parse(rest, CultureInfo.InvariantCulture);
                    pending.AddRange(d.Check(now));
                    break;
                case "expect":
                    Expect(d.Snapshot(now).ToFields(), rest, where);
                    break;
                case "warnings":
                {
                    int n = int.Parse(rest, CultureInfo.InvariantCulture);
                    Check(pending.Count == n, where + ": " + pending.Count + " warnings [" + string.Join(" | ", pending.ToArray()) + "]");
                    pending.Clear();
                    break;
                }
                case "warning":
                    Check(pending.Exists(delegate (string x) { return x.Contains(rest); }),
                          where + ": not among [" + string.Join(" | ", pending.ToArray()) + "]");
                    break;
                default:
                    Check(false, where + ": unknown step");
                    break;
            }
        }
        Check(next == frames.Count, "the script fed all " + frames.Count + " frames (fed " + next + ")");
    }

    static void Expect(Dictionary<string, string> fields, string spec, string where)
    {
        string[] p = spec.Split(new[] { ' ' }, 3);
        if (p.Length == 2 && p[1] == "=")
            p = new[] { p[0], p[1], "" };  // `expect FIELD =`: the empty text
        if (p.Length < 3)
        {
            Check(false, where + ": malformed expect");
            return;
        }
        string got;
        if (!fields.TryGetValue(p[0], out got))
        {
            Check(false, where + ": no field " + p[0]);
            return;
        }
        if (p[1] == "=")
        {
            Check(got == p[2], where + ": got '" + got + "'");
            return;
        }
        string[] v = p[2].Split(' ');
        double want = double.Parse(v[0], CultureInfo.InvariantCulture);
        double tol = double.Parse(v[1], CultureInfo.InvariantCulture);
        double value;
        bool isNumber = double.TryParse(got, NumberStyles.Float, CultureInfo.InvariantCulture, out value);
        Check(p[1] == "~" && isNumber && Math.Abs(value - want) <= tol, where + ": got " + got);
    }

    public static int Main(string[] args)
    {
        try
        {
            UnitTests();
            if (args.Length == 2)
                Replay(args[0], args[1]);
            else if (args.Length != 0)
                Check(false, "usage: GsoeCoreTests.exe [FRAMES.tlog SCRIPT]");
        }
        catch (Exception e)
        {
            Check(false, "exception: " + e);
        }
        Console.WriteLine(_passed + " passed, " + _failed + " failed");
        return _failed == 0 ? 0 : 1;
    }
}
