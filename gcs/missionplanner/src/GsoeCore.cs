// GSOE ground-station core: the companion's MAVLink messages -> one display state.
//
// Pure: no Mission Planner type, no UI, no clock, no I/O. It uses only the MAVLink C# library that pymavlink's
// `mavgen --lang=CS` generates (the same library Mission Planner is built on: MAVLink.MAVLinkMessage and the
// mavlink_*_t structs), so it is tested on Linux with Mono on bytes from the companion's own encoder.
// C# 5 language level on purpose (no string interpolation, no ?., no expression-bodied members): Mission Planner
// compiles a plugin's .cs with Roslyn and, when that fails, with CodeDom (C# 5).
//
// Conventions (as in the companion, nav/link.py and nav/gcs_display.py): speeds m/s, angles degrees (a display
// edge), the wind direction is where the wind blows FROM (0 north, clockwise); WIND_COV wind_x/wind_y are the
// air's velocity north/east (blowing TO).  Times are the caller's clock in seconds (nowS); nothing here reads a
// clock.  Units are in the names: _m_s, _deg, _s.
//
// What the companion sends from component 191 (MAV_COMP_ID_ONBOARD_COMPUTER) and what is made of it:
//   WIND_COV     wind N/E, horiz_accuracy = 1-sigma of the speed, var_horiz = RMS axis sigma (-> direction sigma)
//   WIND         direction (from) and speed (ArduPilot dialect)
//   NAMED_VALUE_FLOAT GSOE_DRIFT, GSOE_ATA (deg), GSOE_Q (0..1), GSOE_GNSS (0 OK, 1 DEGRADED, 2 DENIED),
//                GSOE_VALID (1 sent, 0 withheld); or DEBUG_VECT "GSOE" (x drift deg, y ATA deg, z quality)
//   STATUSTEXT   "GSOE invalid: <reason>", "GSOE estimate valid", "GSOE GNSS_<STATE>: <why>"
// WIND, WIND_COV, GSOE_DRIFT/ATA are sent only while the estimate is valid: the time since the last of them is
// the estimate's age.  GSOE_Q/GNSS/VALID are sent whatever the validity: no GSOE_VALID for StaleS seconds means the
// companion went silent.

using System;
using System.Collections.Generic;
using System.Globalization;
using System.Text;

namespace GsoeNav
{
    /// <summary>What the ground station knows of the estimate's validity.</summary>
    public enum GsoeValidity
    {
        Unknown = 0,
        Valid = 1,
        Invalid = 2,
        Stale = 3,
    }

    /// <summary>A copy of the display state at one time (NaN / empty where nothing was received).</summary>
    public sealed class GsoeDisplayState
    {
        public double WindSpeed_m_s = double.NaN;
        public double WindFrom_deg = double.NaN;
        public double WindSpeedSigma_m_s = double.NaN;
        public double WindFromSigma_deg = double.NaN;
        public double WindNorth_m_s = double.NaN;
        public double WindEast_m_s = double.NaN;
        public double Drift_deg = double.NaN;
        public double Ata_deg = double.NaN;
        public double Quality = double.NaN;
        public string GnssState = "";
        public string GnssReason = "";
        public GsoeValidity Validity = GsoeValidity.Unknown;
        public string InvalidReason = "";
        /// <summary>Seconds since the estimate (wind or drift) last arrived; NaN before the first.</summary>
        public double EstimateAge_s = double.NaN;
        /// <summary>Seconds since the companion's status (GSOE_VALID) last arrived; NaN before the first.</summary>
        public double StatusAge_s = double.NaN;
        public string LastStatusText = "";
        public Dictionary<string, int> Counts = new Dictionary<string, int>();

        /// <summary>A copy of every field (Counts: the same dictionary).</summary>
        public GsoeDisplayState Copy()
        {
            return (GsoeDisplayState)MemberwiseClone();
        }

        /// <summary>Three display lines: wind, drift/ATA, validity/quality/GNSS/age.</summary>
        public string WindLine
        {
            get
            {
                return "Wind " + GsoeFormat.Num(WindSpeed_m_s, "0.0") + "+-" + GsoeFormat.Num(WindSpeedSigma_m_s, "0.0")
                       + " m/s from " + GsoeFormat.Num(WindFrom_deg, "0") + "+-" + GsoeFormat.Num(WindFromSigma_deg, "0")
                       + " deg";
            }
        }

        public string DriftLine
        {
            get
            {
                return "Drift " + GsoeFormat.Num(Drift_deg, "+0.0;-0.0;0.0") + " deg  ATA " + GsoeFormat.Num(Ata_deg, "0.0")
                       + " deg";
            }
        }

        public string StateLine
        {
            get
            {
                string head;
                switch (Validity)
                {
                    case GsoeValidity.Valid:
                        head = "GSOE valid";
                        break;
                    case GsoeValidity.Invalid:
                        head = "GSOE INVALID (" + (InvalidReason.Length > 0 ? InvalidReason : "reason not reported") + ")";
                        break;
                    case GsoeValidity.Stale:
                        head = "GSOE STALE (no status for " + GsoeFormat.Num(StatusAge_s, "0") + " s)";
                        break;
                    default:
                        head = "GSOE unknown";
                        break;
                }
                return head + "  Q " + GsoeFormat.Num(Quality, "0.00") + "  " + (GnssState.Length > 0 ? GnssState : "GNSS ?")
                       + "  age " + GsoeFormat.Num(EstimateAge_s, "0.0") + " s";
            }
        }

        /// <summary>True when the operator should look: invalid, stale, or GNSS not OK.</summary>
        public bool Alarm
        {
            get
            {
                return Validity == GsoeValidity.Invalid || Validity == GsoeValidity.Stale
                       || (GnssState.Length > 0 && GnssState != GsoeDecoder.GnssStateNames[0]);
            }
        }

        /// <summary>Every field as text (invariant culture, "nan" for NaN), snake_case names with units.</summary>
        public Dictionary<string, string> ToFields()
        {
            var d = new Dictionary<string, string>();
            d["wind_speed_m_s"] = GsoeFormat.Raw(WindSpeed_m_s);
            d["wind_from_deg"] = GsoeFormat.Raw(WindFrom_deg);
            d["wind_speed_sigma_m_s"] = GsoeFormat.Raw(WindSpeedSigma_m_s);
            d["wind_from_sigma_deg"] = GsoeFormat.Raw(WindFromSigma_deg);
            d["wind_n_m_s"] = GsoeFormat.Raw(WindNorth_m_s);
            d["wind_e_m_s"] = GsoeFormat.Raw(WindEast_m_s);
            d["drift_deg"] = GsoeFormat.Raw(Drift_deg);
            d["ata_deg"] = GsoeFormat.Raw(Ata_deg);
            d["quality"] = GsoeFormat.Raw(Quality);
            d["gnss_state"] = GnssState;
            d["gnss_reason"] = GnssReason;
            d["validity"] = Validity.ToString();
            d["invalid_reason"] = InvalidReason;
            d["estimate_age_s"] = GsoeFormat.Raw(EstimateAge_s);
            d["status_age_s"] = GsoeFormat.Raw(StatusAge_s);
            d["last_statustext"] = LastStatusText;
            d["alarm"] = Alarm ? "true" : "false";
            d["line_wind"] = WindLine;
            d["line_drift"] = DriftLine;
            d["line_state"] = StateLine;
            foreach (var kv in Counts)
                d["count_" + kv.Key] = kv.Value.ToString(CultureInfo.InvariantCulture);
            return d;
        }
    }

    /// <summary>Number formatting for the display: invariant culture whatever the PC's locale, "--" for NaN.</summary>
    public static class GsoeFormat
    {
        public static string Num(double v, string format)
        {
            if (double.IsNaN(v) || double.IsInfinity(v))
                return "--";
            return v.ToString(format, CultureInfo.InvariantCulture);
        }

        public static string Raw(double v)
        {
            if (double.IsNaN(v) || double.IsInfinity(v))
                return "nan";
            return v.ToString("R", CultureInfo.InvariantCulture);
        }

        /// <summary>An angle in degrees wrapped to [0, 360).</summary>
        public static double Wrap360(double deg)
        {
            double w = deg % 360.0;
            if (w < 0.0)
                w += 360.0;
            return w >= 360.0 ? 0.0 : w;
        }
    }

    /// <summary>
    /// Decodes the companion's messages into the display state and says what the operator must be warned of
    /// (the estimate going invalid, valid again, a GNSS state change, the companion going silent).
    /// Thread-safe: Mission Planner calls Handle from its reader thread and Check/Snapshot from others.
    /// </summary>
    public sealed class GsoeDecoder
    {
        public const byte CompanionComponentId = 191;  // MAV_COMP_ID_ONBOARD_COMPUTER
        public const double DefaultStale_s = 3.0;
        public const string StatusTextPrefix = "GSOE";
        public const string InvalidPrefix = "GSOE invalid: ";
        public const string ValidText = "GSOE estimate valid";
        public const string GnssPrefix = "GSOE GNSS_";
        public const float ValidThreshold = 0.5f;  // GSOE_VALID is 1 or 0
        public static readonly string[] GnssStateNames = { "GNSS_OK", "GNSS_DEGRADED", "GNSS_DENIED" };

        readonly object _lock = new object();
        byte _sourceSystem;
        byte _sourceComponent;
        double _stale_s;

        // what has been received (Snapshot adds the ages, the validity and the counts to a copy)
        readonly GsoeDisplayState _s = new GsoeDisplayState();
        bool? _valid;
        bool _stale;
        double _tEstimate = double.NaN, _tStatus = double.NaN;
        readonly Dictionary<string, int> _counts = new Dictionary<string, int>();

        /// <param name="sourceSystem">the companion's system id (the vehicle's); 0 accepts any</param>
        /// <param name="sourceComponent">the companion's component id (191); 0 accepts any</param>
        /// <param name="stale_s">no GSOE_VALID for this long: the companion is reported silent</param>
        public GsoeDecoder(byte sourceSystem, byte sourceComponent, double stale_s)
        {
            if (!(stale_s > 0.0))
                throw new ArgumentOutOfRangeException("stale_s", "must be > 0");
            _sourceSystem = sourceSystem;
            _sourceComponent = sourceComponent;
            _stale_s = stale_s;
        }

        public GsoeDecoder() : this(0, CompanionComponentId, DefaultStale_s)
        {
        }

        public byte SourceSystem
        {
            get { lock (_lock) return _sourceSystem; }
            set { lock (_lock) _sourceSystem = value; }
        }

        public byte SourceComponent
        {
            get { lock (_lock) return _sourceComponent; }
            set { lock (_lock) _sourceComponent = value; }
        }

        // How each message the decoder reads changes the state (called under the lock, from the companion only).
        delegate void Reader(GsoeDecoder decoder, MAVLink.MAVLinkMessage msg, double nowS, List<string> warn);

        static readonly Dictionary<MAVLink.MAVLINK_MSG_ID, Reader> Readers =
            new Dictionary<MAVLink.MAVLINK_MSG_ID, Reader>
        {
            { MAVLink.MAVLINK_MSG_ID.WIND_COV,
              (d, m, t, w) => d.OnWindCov(m.ToStructure<MAVLink.mavlink_wind_cov_t>(), t) },
            { MAVLink.MAVLINK_MSG_ID.WIND,
              (d, m, t, w) => d.OnWind(m.ToStructure<MAVLink.mavlink_wind_t>(), t) },
            { MAVLink.MAVLINK_MSG_ID.NAMED_VALUE_FLOAT,
              (d, m, t, w) => d.OnNamedValueFloat(m.ToStructure<MAVLink.mavlink_named_value_float_t>(), t, w) },
            { MAVLink.MAVLINK_MSG_ID.DEBUG_VECT,
              (d, m, t, w) => d.OnDebugVect(m.ToStructure<MAVLink.mavlink_debug_vect_t>(), t) },
            { MAVLink.MAVLINK_MSG_ID.STATUSTEXT,
              (d, m, t, w) => d.OnStatusText(m.ToStructure<MAVLink.mavlink_statustext_t>(), w) },
        };

        /// <summary>The message ids the decoder reads (what an adapter subscribes to).</summary>
        public static readonly MAVLink.MAVLINK_MSG_ID[] MessageIds =
            new List<MAVLink.MAVLINK_MSG_ID>(Readers.Keys).ToArray();

        /// <summary>Takes one received message; returns the warnings it causes (empty for most).</summary>
        public List<string> Handle(MAVLink.MAVLinkMessage msg, double nowS)
        {
            var warn = new List<string>();
            Reader read;
            if (msg == null || !Readers.TryGetValue((MAVLink.MAVLINK_MSG_ID)msg.msgid, out read))
                return warn;
            lock (_lock)
            {
                if (FromCompanion(msg.sysid, msg.compid))
                    read(this, msg, nowS, warn);
            }
            return warn;
        }

        bool FromCompanion(byte sysid, byte compid)
        {
            return (_sourceSystem == 0 || sysid == _sourceSystem) && (_sourceComponent == 0 || compid == _sourceComponent);
        }

        void Count(string kind)
        {
            int n;
            _counts.TryGetValue(kind, out n);
            _counts[kind] = n + 1;
        }

        static bool Finite(double v)
        {
            return !double.IsNaN(v) && !double.IsInfinity(v);
        }

        /// <summary>A fixed-size MAVLink char array as text: up to the first NUL (none when it is full).</summary>
        public static string Text(byte[] chars)
        {
            if (chars == null)
                return "";
            int n = Array.IndexOf(chars, (byte)0);
            return Encoding.UTF8.GetString(chars, 0, n < 0 ? chars.Length : n);
        }

        void OnWind(MAVLink.mavlink_wind_t m, double nowS)
        {
            Count("WIND");
            if (!(Finite(m.direction) && Finite(m.speed)))
                return;
            _s.WindSpeed_m_s = m.speed;
            _s.WindFrom_deg = GsoeFormat.Wrap360(m.direction);
            _tEstimate = nowS;
        }

        void OnWindCov(MAVLink.mavlink_wind_cov_t m, double nowS)
        {
            Count("WIND_COV");
            if (!(Finite(m.wind_x) && Finite(m.wind_y) && Finite(m.var_horiz) && Finite(m.horiz_accuracy)))
                return;
            _s.WindNorth_m_s = m.wind_x;
            _s.WindEast_m_s = m.wind_y;
            double speed = Math.Sqrt((double)m.wind_x * m.wind_x + (double)m.wind_y * m.wind_y);
            _s.WindSpeed_m_s = speed;
            // blowing from: the opposite of the air's velocity
            _s.WindFrom_deg = GsoeFormat.Wrap360(Math.Atan2(-(double)m.wind_y, -(double)m.wind_x) * 180.0 / Math.PI);
            _s.WindSpeedSigma_m_s = m.horiz_accuracy;
            // the cross-wind sigma over the speed; near calm the direction is undefined (180 deg)
            _s.WindFromSigma_deg = speed > 0.0 ? Math.Min(Math.PI, m.var_horiz / speed) * 180.0 / Math.PI : 180.0;
            _tEstimate = nowS;
        }

        void OnNamedValueFloat(MAVLink.mavlink_named_value_float_t m, double nowS, List<string> warn)
        {
            string key = Text(m.name);
            if (!key.StartsWith(StatusTextPrefix + "_", StringComparison.Ordinal))
                return;
            Count("NAMED_VALUE_FLOAT");
            float value = m.value;
            if (!Finite(value))
                return;
            if (key == "GSOE_DRIFT")
            {
                _s.Drift_deg = value;
                _tEstimate = nowS;
            }
            else if (key == "GSOE_ATA")
            {
                _s.Ata_deg = GsoeFormat.Wrap360(value);
                _tEstimate = nowS;
            }
            else if (key == "GSOE_Q")
                _s.Quality = value;
            else if (key == "GSOE_GNSS")
                SetGnss(GnssName(value), "", warn);
            else if (key == "GSOE_VALID")
            {
                _tStatus = nowS;
                _stale = false;
                SetValid(value >= ValidThreshold, null, warn);
            }
        }

        void OnDebugVect(MAVLink.mavlink_debug_vect_t m, double nowS)
        {
            if (Text(m.name) != StatusTextPrefix)
                return;
            Count("DEBUG_VECT");
            if (!(Finite(m.x) && Finite(m.y) && Finite(m.z)))
                return;
            _s.Drift_deg = m.x;
            _s.Ata_deg = GsoeFormat.Wrap360(m.y);
            _s.Quality = m.z;
            _tEstimate = nowS;
        }

        void OnStatusText(MAVLink.mavlink_statustext_t m, List<string> warn)
        {
            string t = Text(m.text);
            if (!t.StartsWith(StatusTextPrefix, StringComparison.Ordinal))
                return;
            Count("STATUSTEXT");
            _s.LastStatusText = t;
            if (t.StartsWith(InvalidPrefix, StringComparison.Ordinal))
                SetValid(false, t.Substring(InvalidPrefix.Length).Trim(), warn);
            else if (t.StartsWith(ValidText, StringComparison.Ordinal))
                SetValid(true, null, warn);
            else if (t.StartsWith(GnssPrefix, StringComparison.Ordinal))
            {
                int colon = t.IndexOf(':');
                string state = (colon < 0 ? t.Substring(StatusTextPrefix.Length) : t.Substring(StatusTextPrefix.Length, colon - StatusTextPrefix.Length)).Trim();
                string why = colon < 0 ? "" : t.Substring(colon + 1).Trim();
                SetGnss(state, why, warn);
            }
        }

        static string GnssName(float value)
        {
            int i = (int)Math.Round(value);
            if (i >= 0 && i < GnssStateNames.Length && Math.Abs(value - i) < 1e-3)
                return GnssStateNames[i];
            return "GNSS ? (" + value.ToString("0.###", CultureInfo.InvariantCulture) + ")";
        }

        // A change is announced once, whichever of the named value and the STATUSTEXT comes first.
        void SetGnss(string state, string why, List<string> warn)
        {
            if (state == _s.GnssState)
            {
                if (why.Length > 0)
                    _s.GnssReason = why;
                return;
            }
            if (_s.GnssState.Length > 0)
                warn.Add("GSOE GNSS state " + _s.GnssState + " -> " + state + (why.Length > 0 ? ": " + why : ""));
            _s.GnssState = state;
            _s.GnssReason = why;
        }

        void SetValid(bool valid, string reason, List<string> warn)
        {
            if (valid)
                _s.InvalidReason = "";
            else if (reason != null)
                _s.InvalidReason = reason;
            if (_valid.HasValue && _valid.Value && !valid)
                warn.Add("GSOE estimate INVALID: "
                         + (_s.InvalidReason.Length > 0 ? _s.InvalidReason : "reason not reported")
                         + "; wind and drift no longer sent");
            else if (_valid.HasValue && !_valid.Value && valid)
                warn.Add("GSOE estimate valid again");
            _valid = valid;
        }

        /// <summary>Warnings due to time alone: the companion's status stopped arriving (said once).</summary>
        public List<string> Check(double nowS)
        {
            var warn = new List<string>();
            lock (_lock)
            {
                if (_stale || double.IsNaN(_tStatus) || nowS - _tStatus <= _stale_s)
                    return warn;
                _stale = true;
                warn.Add("GSOE silent for " + (nowS - _tStatus).ToString("0", CultureInfo.InvariantCulture)
                         + " s: estimate unknown");
            }
            return warn;
        }

        /// <summary>The display state at nowS (ages are measured to it).</summary>
        public GsoeDisplayState Snapshot(double nowS)
        {
            GsoeDisplayState s;
            lock (_lock)
            {
                s = _s.Copy();
                s.EstimateAge_s = nowS - _tEstimate;
                s.StatusAge_s = nowS - _tStatus;
                if (_stale)
                    s.Validity = GsoeValidity.Stale;
                else if (_valid.HasValue)
                    s.Validity = _valid.Value ? GsoeValidity.Valid : GsoeValidity.Invalid;
                s.Counts = new Dictionary<string, int>(_counts);
            }
            return s;
        }
    }
}
