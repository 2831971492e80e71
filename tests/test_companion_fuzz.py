"""Hostile MAVLink against the companion over 127.0.0.1 (issue 23), with the simulated vehicle and the companion as
processes and a hostile station (sim.fuzz) injecting seeded bursts into the companion's port: random, truncated and
bit-flipped frames, well-formed messages of random types, in-range spoofed IMU and attitude samples, and telemetry
from foreign senders.

- the default suite: one flight, three bursts of 10^4 packets (seeds 1, 2, 3; 2000 packets/s for 5 s, then 8 s of
  clean data each): no crash, nothing non-finite or out of range reaches the vehicle, the estimate is valid again
  within 5 s of clean data after each burst, and no velocity sent as valid is off by more than 1 m/s or 5 of its
  stated sigmas;
- the late vehicle: the companion first, the vehicle 3.5 s and 6 s later (a slow link start);
- slow: one burst of 10^5 packets (20 s at 5000 packets/s).

``python -m sim.fuzz --seeds 20`` prints the recovery times and the largest velocity error over 20 seeds.
"""

from __future__ import annotations

import numpy as np
import pytest

from common.logio import read_log
from sim.fuzz import Burst, FuzzFlight, fuzz_flight, schedule

RECOVERY_MAX_S = 5.0
VEL_ERROR_MAX_M_S = 1.0
VEL_ERROR_MAX_SIGMA = 5.0
SEEDS = (1, 2, 3)
PACKETS = 10_000


def check_flight(f: FuzzFlight, packets: int) -> None:
    """What every hostile flight must show (module docstring)."""
    assert f.companion_rc == 0, (f.out_dir / "companion.log").read_text()[-3000:]
    assert f.companion, "the companion printed no final status (it crashed)"
    assert f.companion["estimator_errors"] == 0
    assert f.vehicle.get("problems") == [], f.vehicle.get("problems", [])[:10]
    assert sum(f.station.sent.values()) == packets * len(f.bursts), f.station.sent
    rec = f.recovery_s()
    assert all(r is not None and r <= RECOVERY_MAX_S for r in rec), rec
    ve = f.velocity_errors()
    assert len(ve) > 100, "too few estimates sent"
    worst = int(np.argmax(ve[:, 5]))
    assert np.max(np.hypot(ve[:, 1], ve[:, 2])) < VEL_ERROR_MAX_M_S, ve[np.argmax(np.hypot(ve[:, 1], ve[:, 2]))]
    assert ve[worst, 5] < VEL_ERROR_MAX_SIGMA, ve[worst]


@pytest.fixture(scope="module")
def fuzzed(tmp_path_factory: pytest.TempPathFactory) -> FuzzFlight:
    bursts, end = schedule(SEEDS, PACKETS, burst_s=5.0, clean_s=8.0)
    return fuzz_flight(tmp_path_factory.mktemp("fuzz") / "flight", bursts, duration_s=end)


def test_three_bursts_of_10k_hostile_packets_are_survived_and_recovered_from(fuzzed):
    check_flight(fuzzed, PACKETS)


def test_the_spoofed_imu_and_attitude_samples_reached_the_pipeline_and_were_rejected(fuzzed):
    """The link passes what is in range; the pipeline's plausibility tests are what stop the spoofs."""
    r = read_log(fuzzed.log_dir / "samples_rejected.csv")
    kinds = set(r["kind"])
    assert kinds == {"imu", "attitude"}, kinds
    for kind in ("spoofed_imu", "spoofed_attitude", "random_message", "bit_flipped", "truncated", "foreign_sender"):
        assert fuzzed.station.sent.get(kind, 0) > 0.03 * PACKETS, fuzzed.station.sent


def test_telemetry_from_another_component_of_the_autopilots_system_is_refused_by_the_link(fuzzed):
    rejected = fuzzed.companion["telemetry_rejected"]
    foreign = {k: n for k, n in rejected.items() if "from component 1/200, not the autopilot's 1/1" in k}
    assert sum(foreign.values()) > 0, rejected


@pytest.mark.parametrize("delay_s", [3.5, 6.0])
def test_a_vehicle_that_comes_up_late_gives_a_valid_estimate_on_its_gnss(tmp_path, delay_s):
    """The companion starts first, the vehicle ``delay_s`` later (a slow link start): the estimate becomes valid and
    rests on the GNSS fixes, not locked out of them (the issue's run ended 98 m off with every fix refused): the last
    fixes are all fused and the EKF agrees with them within a few metres.  (Whether the first fixes may be withheld
    while the GNSS monitor starts is the monitor's business, issue 23's first item.)"""
    f = fuzz_flight(tmp_path / "flight", [], duration_s=20.0, companion_delay_s=-delay_s)
    assert f.companion_rc == 0 and f.companion["estimator_errors"] == 0
    assert f.vehicle.get("problems") == []
    ve = f.velocity_errors()
    assert len(ve) > 50 and ve[0, 0] < 10.0, ve[:3]
    gnss = read_log(f.log_dir / "gnss.csv")
    ekf = read_log(f.log_dir / "ekf.csv")
    fix = np.isfinite(gnss["pos_n_m"]) & (gnss["t_us"] > ekf["t_us"][0])
    assert fix.sum() > 50
    assert np.all(gnss["fused"][fix][-20:] > 0.5), "healthy fixes refused"
    n = np.interp(gnss["t_us"][fix], ekf["t_us"], ekf["pos_n_m"])
    e = np.interp(gnss["t_us"][fix], ekf["t_us"], ekf["pos_e_m"])
    dist = np.hypot(n - gnss["pos_n_m"][fix], e - gnss["pos_e_m"][fix])
    assert np.median(dist[-20:]) < 5.0, dist[-20:]


@pytest.mark.slow
def test_a_burst_of_100k_hostile_packets_is_survived_and_recovered_from(tmp_path):
    bursts = [Burst(12.0, 32.0, 100_000, 11)]
    f = fuzz_flight(tmp_path / "flight", bursts, duration_s=47.0)
    check_flight(f, 100_000)
