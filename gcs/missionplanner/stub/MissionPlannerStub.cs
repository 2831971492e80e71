// STUB - FOR THE COMPILE CHECK ONLY. NOT MISSION PLANNER, NEVER SHIPPED, NEVER LOADED BY MISSION PLANNER.
//
// The few Mission Planner types and members the GSOE adapter (src/GsoePlugin.cs) uses, with the signatures of
// Mission Planner's own source (ArduPilot/MissionPlanner: Plugin/Plugin.cs, ExtLibs/ArduPilot/Mavlink/
// MAVLinkInterface.cs, ExtLibs/ArduPilot/CurrentState.cs, GCSViews/FlightData.cs, MainV2.cs), so that `mcs`
// can check the adapter and the single-file release on Linux. Bodies do nothing. A real Mission Planner build
// has many more members; if one of those used here is renamed upstream, this stub must follow it.
// The MAVLink types themselves are not stubbed: the check uses the C# library pymavlink's mavgen generates.

using System;
using System.Windows.Forms;

namespace MissionPlanner.Plugin
{
    /// <summary>Plugin/Plugin.cs: the base class Mission Planner instantiates for every type derived from it.</summary>
    public abstract class Plugin
    {
        public System.Reflection.Assembly Assembly = null;

        public PluginHost Host { get; internal set; }

        public abstract string Name { get; }
        public abstract string Version { get; }
        public abstract string Author { get; }

        public virtual DateTime NextRun { get; set; }

        public abstract bool Init();

        public abstract bool Loaded();

        public virtual bool SetupUI(int gui = 0, object data = null)
        {
            return true;
        }

        public virtual bool Loop()
        {
            return true;
        }

        public virtual float loopratehz { get; set; }

        public abstract bool Exit();
    }

    /// <summary>Plugin/Plugin.cs PluginHost: the members the adapter reads.</summary>
    public class PluginHost
    {
        public MainV2 MainForm
        {
            get { return MainV2.instance; }
        }

        public CurrentState cs
        {
            get { return MainV2.comPort.MAV.cs; }
        }

        public MAVLinkInterface comPort
        {
            get { return MainV2.comPort; }
        }
    }
}

namespace MissionPlanner
{
    /// <summary>MainV2.cs: the main form.</summary>
    public class MainV2 : Form
    {
        public static MainV2 instance;
        public static MAVLinkInterface comPort = new MAVLinkInterface();
        public GCSViews.FlightData FlightData;
    }

    /// <summary>ExtLibs/ArduPilot/Mavlink/MAVLinkInterface.cs (there it derives from the MAVLink class).</summary>
    public class MAVLinkInterface
    {
        public uint sysidcurrent { get; set; }

        public int compidcurrent { get; set; }

        public MAVState MAV { get; set; }

        /// <summary>Exact (sysid, compid) match, or (0, 0): the current vehicle's own component only.</summary>
        public int SubscribeToPacketType(MAVLink.MAVLINK_MSG_ID msgid, Func<MAVLink.MAVLinkMessage, bool> function,
            uint sysid, byte compid, bool exclusive = false)
        {
            return 0;
        }

        public void UnSubscribeToPacketType(int id)
        {
        }
    }

    /// <summary>ExtLibs/ArduPilot/Mavlink/MAVState.cs: one vehicle component.</summary>
    public class MAVState
    {
        public CurrentState cs { get; set; }
    }

    /// <summary>ExtLibs/ArduPilot/CurrentState.cs: messageHigh is the HUD's red message line.</summary>
    public class CurrentState
    {
        public string messageHigh { get; set; }
    }
}

namespace MissionPlanner.GCSViews
{
    /// <summary>GCSViews/FlightData.cs: the Flight Data screen; tabControlactions holds its lower-left tabs.</summary>
    public class FlightData : UserControl
    {
        public TabControl tabControlactions = new TabControl();
    }
}
