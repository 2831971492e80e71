"""A writer that asks the Decimator first (``wants``) and builds only the records it would write logs exactly what
handing it every record logs; so does the pipeline with the simulator's decimated sink."""

from __future__ import annotations

import numpy as np

from common.logio import Decimator

PERIODS = {"imu": 0.1, "aid_status": 0.2}
KEYS = {"aid_status": ("source", "rejected")}


def _records(rng: np.random.Generator) -> list[tuple[str, dict]]:
    out = []
    t = 0
    for _ in range(5000):
        t += int(rng.integers(1000, 20_000))
        stream = rng.choice(["imu", "aid_status", "gnss"])
        rec = {"t_us": t, "v": float(rng.normal())}
        if stream == "aid_status":
            rec.update(source=str(rng.choice(["optical", "airspeed"])), rejected=bool(rng.random() < 0.3))
        out.append((str(stream), rec))
    return out


def test_asking_first_writes_the_same_records_and_counts_the_same_drops():
    recs = _records(np.random.default_rng(3))
    all_in: list = []
    asked: list = []
    d1 = Decimator(lambda s, r: all_in.append((s, r)), PERIODS, KEYS)
    d2 = Decimator(lambda s, r: asked.append((s, r)), PERIODS, KEYS)
    for stream, rec in recs:
        d1(stream, rec)
        key = tuple(rec[c] for c in KEYS.get(stream, ()))
        if d2.wants(stream, rec["t_us"], *key):
            d2(stream, rec)
    assert asked == all_in and d1.dropped == d2.dropped and 0 < len(all_in) < len(recs)
