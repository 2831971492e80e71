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
