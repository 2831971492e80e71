"""The EKF state divergence guard (issue 23): is the filter still describing a flying aircraft?

Plausibility tests (:mod:`pipeline.plausibility`) keep implausible samples out; this guard catches a state that
went wrong anyway (samples that passed them, a spoofer consistent with itself, a numerical accident).  It judges
the EKF's estimate and its aid sources' status records, each test with a named threshold in ``[pipeline]``
(:class:`pipeline.navpipeline.PipelineConfig`; a threshold of 0 switches its test off):

``ground speed``
    the horizontal ground speed above ``guard_max_ground_speed_m_s`` (the airframe's top speed plus the strongest
    wind it flies in);
``vertical speed``
    ``|vel_d|`` above ``guard_max_vertical_speed_m_s``;
``height``
    the height above the origin's ground level outside ``[guard_min_height_m, guard_max_height_m]``;
``non-finite state``
    a position or velocity that is not a finite number;
``aid sources all failing``
    for ``guard_all_fail_s`` every sample of the sensors that measure the velocity (:data:`VELOCITY_AIDS`:
    airspeed, optical, GNSS velocity) was refused by its innovation gate, none fused, and at least
    ``guard_min_failing_sources`` of them were refused: every such sensor disagrees with the state, so the state
    is what is wrong (one source refused alone is that source's fault, which its gate is there for).  The velocity
    is what the IMU's errors go into first; the other sources go on fusing while it is wrong (the baro, the GNSS
    position, whose error grows slowly, the sideslip and angle of attack, which see only the air velocity's
    direction), so they do not count.
``GNSS velocity refused``
    for ``guard_all_fail_s`` every GNSS velocity was refused by its gate, none fused.  The pipeline fuses GNSS only
    while it is enabled (the companion: while its GNSS monitor says the receiver is healthy), so the state is what
    is wrong, even when another aid still agrees with it (corrupted IMU samples can corrupt the optical
    estimator's gyro bias too; docs/pipeline.md); the EKF's own reset to GNSS (``[ekf] gnss.reset_after_s``) comes
    later.

From the first such refusal on (the first refused GNSS velocity, or the refusals of at least
``guard_min_failing_sources`` velocity aids, none fused since), the state is *suspect*
(:attr:`DivergenceGuard.suspect`): its estimate is not valid until the test's time has passed, and it is valid again
as soon as one of them fuses.

The bounds are checked on every estimate handed out (:meth:`DivergenceGuard.bounds`, a few comparisons: an estimate
beyond them is never valid); the whole test with the aid records runs when the pipeline records the estimate
(:meth:`DivergenceGuard.check`, every camera frame and every ``ekf_record_period_s``).  What the pipeline does about
a divergence (drop the filter, restart it through its one start policy, announce both) is
:class:`pipeline.navpipeline.NavPipeline`'s; what it announces is a :class:`GuardEvent`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

from fusion.ekf import REASON_GATE, AidStatus, NavEstimate

if TYPE_CHECKING:
    from pipeline.navpipeline import PipelineConfig

US_PER_S = 1_000_000
#: the aid sources that measure the ground or air velocity (``aid sources all failing``)
VELOCITY_AIDS = ("airspeed", "optical", "gnss_vel")
GNSS_VEL = "gnss_vel"
STATUSTEXT_MAX_CHARS = 50  # a MAVLink STATUSTEXT's text


#: the guard's tests, each reason starting with its name
TESTS = ("non-finite state", "ground speed", "vertical speed", "height", "GNSS velocity refused",
         "aid sources all failing")


def reason_test(why: str) -> str:
    """The test that gave the reason ``why``."""
    return next((t for t in TESTS if why.startswith(t)), why)


@dataclass(frozen=True, slots=True)
class GuardEvent:
    """Something the pipeline did to the EKF that the crew must hear of: ``kind`` is ``"diverged"`` (the filter
    was dropped and its outputs are invalid) or ``"reset"`` (restarted, or its position/velocity reset to GNSS);
    ``reason`` the full explanation for the log, ``text`` the STATUSTEXT to send (at most 50 characters)."""

    t_us: int
    kind: str
    reason: str
    text: str

    @classmethod
    def make(cls, t_us: int, kind: str, reason: str, text: str) -> GuardEvent:
        return cls(int(t_us), kind, reason, text[:STATUSTEXT_MAX_CHARS])

    def as_record(self) -> dict[str, object]:
        """Flat record for the ``ekf_events`` stream."""
        return {"t_us": self.t_us, "kind": self.kind, "reason": self.reason}


class DivergenceGuard:
    """The tests of the module docstring.  :meth:`bounds` on any estimate, :meth:`check` at each record;
    :meth:`restart` when the pipeline starts a new filter (its aid records begin afresh)."""

    def __init__(self, cfg: PipelineConfig) -> None:
        self.cfg = cfg
        self._fail_us = round(cfg.guard_all_fail_s * US_PER_S)
        self.restart()

    def restart(self) -> None:
        """Forget the aid records seen (a new filter's counters start at 0)."""
        self._n_rejected: dict[str, int] = {}
        self._failing_since_us: int | None = None
        self._failing: set[str] = set()
        self._gnss_since_us: int | None = None

    @property
    def failing(self) -> bool:
        """Whether a velocity aid was refused by its gate since the last one fused, or the GNSS velocity since it
        last fused."""
        return self._failing_since_us is not None or self._gnss_since_us is not None

    @property
    def failing_since_us(self) -> int | None:
        """The stamp of the first refusal of :attr:`failing` (None: not failing)."""
        return min((t for t in (self._failing_since_us, self._gnss_since_us) if t is not None), default=None)

    @property
    def suspect(self) -> str:
        """Why the state is suspect at the last :meth:`check` ("" when it is not; module docstring)."""
        if self._gnss_since_us is not None:
            return "GNSS velocity refused"
        if len(self._failing) < self.cfg.guard_min_failing_sources:
            return ""
        return f"every velocity aid refused ({', '.join(sorted(self._failing))})"

    def bounds(self, e: NavEstimate) -> str:
        """Why the estimate's kinematic state is beyond what the airframe can do ("" when it is not)."""
        c = self.cfg
        vn, ve, vd = (float(v) for v in e.vel_ned_m_s)
        pn, pe = (float(p) for p in e.pos_ne_m)
        h = float(e.height_m)
        if not all(math.isfinite(v) for v in (vn, ve, vd, pn, pe, h)):
            return "non-finite state"
        gs = math.hypot(vn, ve)
        if c.guard_max_ground_speed_m_s and gs > c.guard_max_ground_speed_m_s:
            return f"ground speed {gs:.0f} m/s > {c.guard_max_ground_speed_m_s:g}"
        if c.guard_max_vertical_speed_m_s and abs(vd) > c.guard_max_vertical_speed_m_s:
            return f"vertical speed {abs(vd):.0f} m/s > {c.guard_max_vertical_speed_m_s:g}"
        if c.guard_max_height_m and not c.guard_min_height_m <= h <= c.guard_max_height_m:
            return f"height {h:.0f} m outside [{c.guard_min_height_m:g}, {c.guard_max_height_m:g}]"
        return ""

    def check(self, e: NavEstimate, status: dict[str, AidStatus]) -> str:
        """Why the filter has diverged ("" when it has not): :meth:`bounds`, then the aid sources' records since
        the last call (module docstring)."""
        why = self.bounds(e)
        if why or not self._fail_us:
            return why
        aids = [(name, st) for name, st in status.items() if name in VELOCITY_AIDS]
        refused = {name: st for name, st in aids if st.n_rejected > self._n_rejected.get(name, 0) and st.rejected
                   and st.reason == REASON_GATE}
        self._n_rejected.update((name, st.n_rejected) for name, st in aids)
        # every velocity aid refused, none fused since the first refusal
        last_fuse = max((st.t_last_fuse_us for _, st in aids), default=-1)
        since = self._failing_since_us
        if since is not None and last_fuse >= since:
            since, self._failing = None, set()      # a source fused after the failures began: not all failing
        for name, st in refused.items():
            if st.t_us > last_fuse:
                self._failing.add(name)
                since = st.t_us if since is None else min(since, st.t_us)
        self._failing_since_us = since
        # the GNSS velocity refused, not fused since
        gnss, g_since = status.get(GNSS_VEL), self._gnss_since_us
        if gnss is not None and g_since is not None and gnss.t_last_fuse_us >= g_since:
            g_since = None
        if GNSS_VEL in refused and g_since is None and refused[GNSS_VEL].t_us > refused[GNSS_VEL].t_last_fuse_us:
            g_since = refused[GNSS_VEL].t_us
        self._gnss_since_us = g_since
        if g_since is not None and e.t_us - g_since >= self._fail_us:
            return f"GNSS velocity refused for {(e.t_us - g_since) / US_PER_S:.1f} s (the receiver healthy)"
        if since is None or len(self._failing) < self.cfg.guard_min_failing_sources or e.t_us - since < self._fail_us:
            return ""
        return f"aid sources all failing for {(e.t_us - since) / US_PER_S:.1f} s ({', '.join(sorted(self._failing))})"
