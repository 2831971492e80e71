"""Shared test fixtures."""

from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SHARED_DATA = ROOT.parent / "shared" / "data"


@pytest.fixture(scope="session")
def gsoe_config():
    from pipeline.config import load_gsoe_config

    return load_gsoe_config()[0]


@pytest.fixture(scope="session")
def camera(gsoe_config):
    from gsoe.camera import CameraModel

    return CameraModel.from_config(gsoe_config.camera)


def shared_data(*parts: str) -> Path:
    """A path under ../shared/data; the calling test is skipped when it is absent."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"{p} not available (../shared/data is absent)")
    return p


#: Test files that take minutes (SIL flights in real time, long simulations), longest first: collected first, so
#: that the two xdist workers of ``make test`` (``--dist loadfile``) start them at once and the short files fill in
#: around them, instead of one long file running alone at the end.
LONG_FILES = ("test_measured_flown.py", "test_arduplane_sitl.py", "test_sim.py", "test_companion_fuzz.py",
              "test_companion_faults.py", "test_companion_e2e.py", "test_montecarlo.py", "test_gcs.py",
              "test_companion.py", "test_fusion_wind_model.py")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    rank = {name: i for i, name in enumerate(LONG_FILES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(LONG_FILES)))  # stable: the rest keep their order
