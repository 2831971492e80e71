"""The Mission Planner plugin (gcs/missionplanner/): its C# core on the companion's own bytes, with Mono.

A short companion story is encoded with the companion's encoder (:func:`nav.link.encode_outputs`,
:func:`nav.link.status_values`, :func:`nav.link.check_estimate`, the GNSS monitor's announcements) and pymavlink,
as MAVLink 2 from system 1, component 191 (plus the autopilot's own WIND from component 1, which must be
ignored), and written as a telemetry log (8-byte big-endian receive time + packet).  The compiled C# test runner
(gcs/missionplanner/tests/GsoeCoreTests.cs) replays it through the core against a script of expectations computed
here from the same estimates, and runs its own unit tests; it prints ``N passed, N failed``.  The wind and drift
display lines are also cross-checked against :class:`nav.gcs_display.GsoeGroundState` (the MAVProxy module's
state, an independent implementation) fed the same packets.

The build (gcs/missionplanner/build.py) generates the MAVLink C# library with pymavlink's ``mavgen --lang=CS``
into a scratch folder, compiles the core, the test runner, and the single-file release against a stub of Mission
Planner's API.  Without ``mcs``/``mono`` (``apt-get install -y mono-devel``; .ci/run installs it on CI) those tests
are skipped; the check that the single file is the core and the adapter runs everywhere.  The single file is a
build product (``make missionplanner-plugin``), not tracked: these tests generate it where they need it.
"""

from __future__ import annotations

import importlib.util
import math
import os
import re
import struct
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

from common.angles import wrap_360  # noqa: E402
from common.samples import GnssSample  # noqa: E402
from nav.gcs_display import GsoeGroundState  # noqa: E402
from nav.gnss_monitor import GnssMonitor, GnssMonitorConfig, GnssState  # noqa: E402
from nav.link import (  # noqa: E402
    MAV_COMP_ID_ONBOARD_COMPUTER,
    MAV_SEVERITY,
    LinkConfig,
    OutputEstimate,
    check_estimate,
    encode_outputs,
    status_values,
    wind_from_deg,
    wind_sigmas,
)

ROOT = Path(__file__).resolve().parent.parent
AUTOPILOT_COMPONENT = 1
SYSTEM_ID = 1
STATUSTEXT_CHARS = 50  # MAVLink STATUSTEXT text field (the companion cuts its texts to it)
INVALID_PREFIX = "GSOE invalid: "  # nav.companion's text when the estimate goes invalid
VALID_TEXT = "GSOE estimate valid"  # ... and when it is valid again
FLOAT32_TOL = 1e-4  # m/s, 0..1: values pass through float32
DEG_TOL = 1e-3  # degrees through float32 (|angle| < 360)
ALL_KINDS = {"named", "vision", "wind"}


def _load_build() -> ModuleType:
    spec = importlib.util.spec_from_file_location("gsoe_mp_build", ROOT / "gcs" / "missionplanner" / "build.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod


build = _load_build()


# ------------------------------------------------------------------------------------------------ the story
@dataclass
class Story:
    """Frames as a ground station receives them, and the runner's script (see GsoeCoreTests.cs)."""

    frames: list[tuple[int, bytes]] = field(default_factory=list)
    script: list[str] = field(default_factory=list)
    unfed: int = 0
    reference: GsoeGroundState = field(default_factory=GsoeGroundState)
    _senders: dict[int, Any] = field(default_factory=dict)
    _parser: Any = None

    def send(self, t_s: float, name: str, fields: dict[str, Any],
             component: int = MAV_COMP_ID_ONBOARD_COMPUTER) -> None:
        """One message as pymavlink packs it for (system 1, ``component``); the reference state receives it too."""
        mav = self._senders.setdefault(component, mavlink.MAVLink(None, srcSystem=SYSTEM_ID, srcComponent=component))
        args = {k: v.encode() if isinstance(v, str) else v for k, v in fields.items()}
        buf = getattr(mav, name.lower() + "_encode")(**args).pack(mav)
        self.frames.append((round(t_s * 1e6), bytes(buf)))
        self.unfed += 1
        if self._parser is None:
            self._parser = mavlink.MAVLink(None)
        for msg in self._parser.parse_buffer(buf) or []:
            self.reference.update(msg, t_s)

    def feed(self) -> None:
        self.script.append(f"feed {self.unfed}")
        self.unfed = 0

    def expect(self, name: str, value: float | str, tol: float | None = None) -> None:
        if isinstance(value, str):
            self.script.append(f"expect {name} = {value}".rstrip())
        else:
            assert tol is not None and math.isfinite(value)
            self.script.append(f"expect {name} ~ {value!r} {tol!r}")

    def warnings(self, n: int, *contains: str) -> None:
        self.script += [f"warning {c}" for c in contains] + [f"warnings {n}"]

    def write(self, folder: Path) -> tuple[Path, Path]:
        assert self.unfed == 0, "frames not fed by the script"
        tlog, script = folder / "companion.tlog", folder / "companion.script"
        tlog.write_bytes(b"".join(struct.pack(">Q", t_us) + buf for t_us, buf in self.frames))
        script.write_text("\n".join(self.script) + "\n", encoding="utf-8")
        return tlog, script


def companion_step(story: Story, t_s: float, est: OutputEstimate, cfg: LinkConfig) -> str:
    """What CompanionLink.send_estimate sends for ``est`` (every output due): the status named values, then the
    estimate's messages when it passes check_estimate; returns the reason it did not."""
    reason = check_estimate(est, cfg)
    t_ms = int(t_s * 1000)
    for name, v in status_values(est, not reason).items():
        story.send(t_s, "NAMED_VALUE_FLOAT", {"time_boot_ms": t_ms, "name": name, "value": v})
    if not reason:
        for name, fields in encode_outputs(est, cfg, ALL_KINDS).values():
            story.send(t_s, name, fields)
    return reason


def statustext(story: Story, t_s: float, text: str, severity: str) -> None:
    """CompanionLink.send_statustext's fields."""
    story.send(t_s, "STATUSTEXT", {"severity": MAV_SEVERITY[severity], "text": text[:STATUSTEXT_CHARS], "id": 0,
                                   "chunk_seq": 0})


def estimate(t_s: float, wind_ne_m_s: tuple[float, float], drift_deg: float, ata_deg: float, quality: float,
             gnss: GnssState, valid: bool = True, reason: str = "") -> OutputEstimate:
    wind_cov = np.array([[0.09, 0.01], [0.01, 0.16]])
    return OutputEstimate(
        t_us=round(t_s * 1e6), valid=valid, drift_rad=math.radians(drift_deg), drift_sigma_rad=math.radians(0.4),
        ata_rad=math.radians(ata_deg), vel_ne_m_s=np.array([20.0, 7.0]), vel_cov_ne=np.diag([0.25, 0.25]),
        wind_ne_m_s=np.array(wind_ne_m_s), wind_cov_ne=wind_cov, height_agl_m=250.0, quality=quality,
        gnss_state=int(gnss), reason=reason, home_amsl_m=310.0)


def expect_estimate(story: Story, est: OutputEstimate, *, named: bool = True) -> None:
    """The display values the companion's encoder implies for ``est``."""
    speed = float(np.hypot(*est.wind_ne_m_s))
    speed_sigma, rms = wind_sigmas(est.wind_ne_m_s, est.wind_cov_ne)
    story.expect("wind_speed_m_s", speed, FLOAT32_TOL)
    story.expect("wind_from_deg", wind_from_deg(est.wind_ne_m_s), DEG_TOL)
    story.expect("wind_n_m_s", float(est.wind_ne_m_s[0]), FLOAT32_TOL)
    story.expect("wind_e_m_s", float(est.wind_ne_m_s[1]), FLOAT32_TOL)
    story.expect("wind_speed_sigma_m_s", speed_sigma, FLOAT32_TOL)
    story.expect("wind_from_sigma_deg", math.degrees(min(math.pi, rms / speed)), DEG_TOL)
    story.expect("drift_deg", math.degrees(est.drift_rad), DEG_TOL)
    story.expect("ata_deg", float(wrap_360(math.degrees(est.ata_rad))), DEG_TOL)
    story.expect("quality", est.quality, FLOAT32_TOL)
    if named:
        story.expect("gnss_state", GnssState(est.gnss_state).name)


def expect_reference_lines(story: Story) -> None:
    """The wind and drift lines as the MAVProxy module's state (nav.gcs_display) writes them."""
    lines = story.reference.lines()
    story.expect("line_wind", lines["GSOEWind"])
    story.expect("line_drift", lines["GSOEDrift"])


def gnss_announcements(monitor: GnssMonitor, t_s: float, fix_ok: bool) -> list[str]:
    """The GNSS monitor's own STATUSTEXTs for a fix (with or without) at ``t_s``."""
    nan3 = np.full(3, math.nan)
    pos = np.zeros(3) if fix_ok else nan3
    sample = GnssSample(round(t_s * 1e6), pos, np.zeros(3) if fix_ok else nan3, fix_ok=fix_ok,
                        n_sats=12 if fix_ok else 2, h_acc_m=1.0 if fix_ok else math.inf)
    return [a.text for a in monitor.update(sample)]


def companion_story() -> Story:
    """Valid -> the autopilot's WIND (ignored) -> GNSS denied -> estimate invalid -> silent -> valid again with
    DEBUG_VECT and WIND_COV only, GNSS recovered."""
    s = Story()
    cfg = LinkConfig()

    a = estimate(0.0, (0.0, 8.0), drift_deg=21.5, ata_deg=-37.3, quality=0.97, gnss=GnssState.GNSS_OK)
    assert companion_step(s, 0.0, a, cfg) == ""
    s.feed()
    expect_estimate(s, a)
    s.expect("validity", "Valid")
    s.expect("estimate_age_s", 0.0, 1e-9)
    s.expect("count_WIND", "1")
    s.expect("count_WIND_COV", "1")
    s.expect("count_NAMED_VALUE_FLOAT", "5")
    expect_reference_lines(s)
    s.warnings(0)

    # the autopilot's own wind estimate, from component 1: not the companion's
    s.send(0.5, "WIND", {"direction": 90.0, "speed": 3.0, "speed_z": 0.0}, component=AUTOPILOT_COMPONENT)
    s.feed()
    expect_estimate(s, a)
    s.expect("count_WIND", "1")
    expect_reference_lines(s)
    s.warnings(0)

    monitor = GnssMonitor(GnssMonitorConfig(), initial=GnssState.GNSS_OK)
    [denied] = gnss_announcements(monitor, 1.0, fix_ok=False)
    statustext(s, 1.0, denied, "warning")
    b = estimate(1.0, (-3.0, 4.0), drift_deg=-6.7, ata_deg=112.5, quality=0.61, gnss=GnssState.GNSS_DENIED)
    assert companion_step(s, 1.0, b, cfg) == ""
    s.feed()
    expect_estimate(s, b)
    s.expect("gnss_reason", denied.split(": ", 1)[1])
    s.expect("alarm", "true")
    expect_reference_lines(s)
    s.warnings(1, "GSOE GNSS state GNSS_OK -> GNSS_DENIED: " + denied.split(": ", 1)[1])

    c = replace(b, t_us=2_000_000, valid=False, reason="drift sigma 3.4 deg above its 3.0 deg gate")
    reason = check_estimate(c, cfg)
    text = (INVALID_PREFIX + reason)[:STATUSTEXT_CHARS]
    assert len(INVALID_PREFIX + reason) > STATUSTEXT_CHARS  # the reason arrives cut
    statustext(s, 2.0, text, "warning")
    assert companion_step(s, 2.0, c, cfg) == reason
    s.feed()
    s.expect("validity", "Invalid")
    s.expect("invalid_reason", text[len(INVALID_PREFIX):].strip())
    expect_estimate(s, b)  # the last values stay on show, getting older
    s.warnings(1, "GSOE estimate INVALID: " + text[len(INVALID_PREFIX):].strip())
    for t_s in (2.2, 2.4):
        companion_step(s, t_s, replace(c, t_us=round(t_s * 1e6)), cfg)
    s.feed()
    s.expect("estimate_age_s", 1.4, 1e-6)
    s.expect("status_age_s", 0.0, 1e-9)
    s.warnings(0)

    s.script.append("check 5.0")  # 2.6 s without status: not yet silent (3 s)
    s.warnings(0)
    s.script.append("check 6.0")
    s.expect("validity", "Stale")
    s.warnings(1, "GSOE silent for 4 s")

    # valid again; this companion sends DEBUG_VECT instead of named values, and no ArduPilot WIND
    cfg2 = LinkConfig(named_values="debug_vect", wind_ardupilot=False)
    assert gnss_announcements(monitor, 100.0, fix_ok=True) == []  # recovery waits recover_after_s
    [recovered] = gnss_announcements(monitor, 100.0 + monitor.config.recover_after_s + 1.0, fix_ok=True)
    statustext(s, 7.0, recovered, "info")
    statustext(s, 7.0, VALID_TEXT, "info")
    d = estimate(7.0, (2.5, 2.5), drift_deg=3.25, ata_deg=250.0, quality=0.88, gnss=GnssState.GNSS_OK)
    assert companion_step(s, 7.0, d, cfg2) == ""
    s.feed()
    expect_estimate(s, d)
    s.expect("validity", "Valid")
    s.expect("invalid_reason", "")
    s.expect("alarm", "false")
    s.expect("count_DEBUG_VECT", "1")
    s.expect("count_WIND", "2")  # a and b: none from d, none from the autopilot
    s.expect("count_WIND_COV", "3")
    s.warnings(2, "GSOE GNSS state GNSS_DENIED -> GNSS_OK", "GSOE estimate valid again")
    return s


# ------------------------------------------------------------------------------------------------ tests
_USING = re.compile(r"using [\w.]+;")


def _code_and_usings(text: str) -> tuple[list[str], set[str]]:
    """A C# file's code lines (no comments, blanks or ``using`` directives) in order, and its directives."""
    lines = [ln.strip() for ln in text.lstrip("\ufeff").splitlines()]
    usings = {ln for ln in lines if _USING.fullmatch(ln)}
    return [ln for ln in lines if ln and not ln.startswith("//") and ln not in usings], usings


def test_the_single_file_is_the_core_then_the_adapter(tmp_path: Path) -> None:
    release = build.write_release(tmp_path / "GsoeNavPlugin.cs").read_text(encoding="utf-8")
    code, usings = _code_and_usings(release)
    parts = [_code_and_usings(p.read_text(encoding="utf-8")) for p in (build.CORE, build.ADAPTER)]
    assert code == parts[0][0] + parts[1][0]
    assert usings == parts[0][1] | parts[1][1]
    assert release.index("using ") < release.index("namespace ")  # C# wants the directives first
    assert len(re.findall(r"class \w+ : MissionPlanner\.Plugin\.Plugin\b", release)) == 1
    assert "STUB" not in release and "namespace MissionPlanner" not in release  # the stub never ships


@pytest.fixture(scope="module")
def csharp(tmp_path_factory: pytest.TempPathFactory) -> Any:
    why = build.missing_tools()
    if why:
        pytest.skip(f"C# tests of the Mission Planner plugin need Mono: {why}")
    return build.build_all(tmp_path_factory.mktemp("missionplanner"))


def test_the_release_compiles_against_mission_planners_plugin_api_stub(csharp: Any) -> None:
    # build_all wrote the release and compiled it (C# 5, warnings as errors) against the stub's MissionPlanner.dll;
    # the core alone too
    assert csharp.release_cs.read_text(encoding="utf-8") == build.release_text()
    assert csharp.release_dll.is_file() and csharp.core_dll.is_file()


def test_the_core_decodes_the_companions_bytes(csharp: Any, tmp_path: Path) -> None:
    story = companion_story()
    tlog, script = story.write(tmp_path)
    p = build.run_tests(csharp, tlog, script)
    out = p.stdout.strip().splitlines()
    assert out, p.stderr
    m = re.fullmatch(r"(\d+) passed, (\d+) failed", out[-1])
    assert m, p.stdout + p.stderr
    n_steps = sum(line.split(" ", 1)[0] in ("expect", "warnings", "warning") for line in story.script)
    assert (p.returncode, int(m[2])) == (0, 0), p.stdout + p.stderr
    assert int(m[1]) > n_steps  # the unit tests ran too, and every step of the script counted


def test_the_runner_fails_on_a_wrong_expectation(csharp: Any, tmp_path: Path) -> None:
    story = companion_story()
    story.script.append("expect wind_speed_m_s ~ 99.0 0.001")
    tlog, script = story.write(tmp_path)
    p = build.run_tests(csharp, tlog, script)
    assert p.returncode != 0
    assert p.stdout.strip().splitlines()[-1].endswith("passed, 1 failed")
