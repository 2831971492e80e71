// GSOE Mission Planner adapter: a thin layer between Mission Planner's plugin API and GsoeNav.GsoeDecoder.
//
// - subscribes to WIND_COV, WIND, NAMED_VALUE_FLOAT, DEBUG_VECT and STATUSTEXT with the companion's ids: the
//   current vehicle's system id and component 191 (a subscription with (0, 0) only matches the autopilot's own
//   component, so the companion's messages would never arrive); re-subscribes when the vehicle or link changes;
// - shows the decoder's three lines in a "GSOE" tab of the Flight Data screen (red while the estimate is invalid,
//   the companion silent or GNSS not OK);
// - raises every warning (estimate invalid with its reason, valid again, GNSS state change, companion silent) on
//   the HUD (CurrentState.messageHigh, the red HUD message line) and in the tab.
//
// Written against Mission Planner's Plugin/Plugin.cs and ExtLibs/ArduPilot/Mavlink/MAVLinkInterface.cs
// (SubscribeToPacketType(MAVLINK_MSG_ID, Func<MAVLinkMessage, bool>, uint sysid, byte compid, bool exclusive)
// returning an int). It is compile-checked here only against a stub of those types
// (gcs/missionplanner/stub/MissionPlannerStub.cs), never run inside Mission Planner by our tests.
// C# 5 language level, as the core.

using System;
using System.Collections;
using System.Collections.Generic;
using System.Diagnostics;
using System.Drawing;
using System.Globalization;
using System.Reflection;
using System.Windows.Forms;

namespace GsoeNav
{
    public class GsoeMissionPlannerPlugin : MissionPlanner.Plugin.Plugin
    {
        const float LoopRate_hz = 2.0f;
        const string TabTitle = "GSOE";
        const int WarningLines = 6;

        readonly GsoeDecoder _decoder = new GsoeDecoder(0, GsoeDecoder.CompanionComponentId, GsoeDecoder.DefaultStale_s);
        readonly Stopwatch _clock = Stopwatch.StartNew();
        readonly object _subLock = new object();
        readonly List<int> _subscriptions = new List<int>();
        readonly object _warnLock = new object();
        readonly List<string> _warnings = new List<string>();
        MissionPlanner.MAVLinkInterface _port;
        uint _sysid;
        TabPage _page;
        Label _windLabel, _driftLabel, _stateLabel, _warningLabel;

        public override string Name
        {
            get { return "GSOE nav display"; }
        }

        public override string Version
        {
            get { return "0.1.0"; }
        }

        public override string Author
        {
            get { return "gsoe-nav"; }
        }

        double NowS()
        {
            return _clock.Elapsed.TotalSeconds;
        }

        public override bool Init()
        {
            loopratehz = LoopRate_hz;
            return true;
        }

        public override bool Loaded()
        {
            BuildTab();
            Resubscribe();
            return true;
        }

        public override bool Loop()
        {
            Resubscribe();
            Warn(_decoder.Check(NowS()));
            ShowState(_decoder.Snapshot(NowS()));
            return true;
        }

        public override bool Exit()
        {
            Unsubscribe();
            if (_page != null && Host.MainForm != null && Host.MainForm.FlightData != null)
                Host.MainForm.FlightData.tabControlactions.TabPages.Remove(_page);
            return true;
        }

        // ------------------------------------------------------------------ MAVLink
        bool OnPacket(MAVLink.MAVLinkMessage msg)
        {
            Warn(_decoder.Handle(msg, NowS()));
            return true;
        }

        void Resubscribe()
        {
            lock (_subLock)
            {
                var port = Host.comPort;
                if (port == null)
                    return;
                uint sysid = (uint)port.sysidcurrent;
                if (ReferenceEquals(port, _port) && sysid == _sysid && _subscriptions.Count > 0)
                    return;
                UnsubscribeLocked();
                _port = port;
                _sysid = sysid;
                _decoder.SourceSystem = (byte)sysid;
                if (sysid == 0)
                    return;  // no vehicle yet: (0, 191) would match nothing
                foreach (var id in GsoeDecoder.MessageIds)
                    _subscriptions.Add(port.SubscribeToPacketType(id, OnPacket, sysid, GsoeDecoder.CompanionComponentId));
            }
        }

        void Unsubscribe()
        {
            lock (_subLock)
                UnsubscribeLocked();
        }

        void UnsubscribeLocked()
        {
            if (_port != null)
                foreach (var sub in _subscriptions)
                    _port.UnSubscribeToPacketType(sub);
            _subscriptions.Clear();
        }

        // ------------------------------------------------------------------ display
        void Warn(List<string> texts)
        {
            if (texts == null || texts.Count == 0)
                return;
            lock (_warnLock)
            {
                foreach (var t in texts)
                    _warnings.Add(DateTime.Now.ToString("HH:mm:ss", CultureInfo.InvariantCulture) + "  " + t);
                while (_warnings.Count > WarningLines)
                    _warnings.RemoveAt(0);
            }
            try
            {
                // the HUD's red message line
                Host.cs.messageHigh = texts[texts.Count - 1];
            }
            catch (Exception)
            {
                // no vehicle state yet: the tab still shows it
            }
        }

        void BuildTab()
        {
            if (Host.MainForm == null || Host.MainForm.FlightData == null)
                return;
            _page = new TabPage(TabTitle);
            var table = new TableLayoutPanel();
            table.Dock = DockStyle.Fill;
            table.ColumnCount = 1;
            table.RowCount = 4;
            _windLabel = NewLabel(12f);
            _driftLabel = NewLabel(12f);
            _stateLabel = NewLabel(12f);
            _warningLabel = NewLabel(9f);
            table.Controls.Add(_windLabel, 0, 0);
            table.Controls.Add(_driftLabel, 0, 1);
            table.Controls.Add(_stateLabel, 0, 2);
            table.Controls.Add(_warningLabel, 0, 3);
            _page.Controls.Add(table);
            var flightData = Host.MainForm.FlightData;
            flightData.tabControlactions.TabPages.Add(_page);
            AddToOriginalTabList(flightData, _page);
        }

        static Label NewLabel(float size)
        {
            var l = new Label();
            l.AutoSize = true;
            l.Font = new Font(FontFamily.GenericMonospace, size);
            l.Text = "--";
            return l;
        }

        // Mission Planner rebuilds the Flight Data tabs from FlightData.TabListOriginal when the user edits them:
        // the page is added there too where this version of Mission Planner has that list.
        static void AddToOriginalTabList(object flightData, TabPage page)
        {
            const BindingFlags flags = BindingFlags.Public | BindingFlags.Instance;
            object list = null;
            var field = flightData.GetType().GetField("TabListOriginal", flags);
            if (field != null)
                list = field.GetValue(flightData);
            else
            {
                var prop = flightData.GetType().GetProperty("TabListOriginal", flags);
                if (prop != null)
                    list = prop.GetValue(flightData, null);
            }
            var ilist = list as IList;
            if (ilist != null && !ilist.Contains(page))
                ilist.Add(page);
        }

        void ShowState(GsoeDisplayState s)
        {
            var form = Host.MainForm;
            if (_page == null || form == null || !form.IsHandleCreated)
                return;
            string warnings;
            lock (_warnLock)
                warnings = string.Join(Environment.NewLine, _warnings.ToArray());
            form.BeginInvoke((MethodInvoker)delegate
            {
                var colour = s.Alarm ? Color.Red : Color.DarkGreen;
                _windLabel.Text = s.WindLine;
                _driftLabel.Text = s.DriftLine;
                _stateLabel.Text = s.StateLine + (s.GnssReason.Length > 0 ? "  (" + s.GnssReason + ")" : "");
                _stateLabel.ForeColor = colour;
                _warningLabel.Text = warnings;
            });
        }
    }
}
