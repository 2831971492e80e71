"""The simulator's disk cache (sim.diskcache): what comes back is what was built, a changed input is rebuilt, and a
cache that is off or cannot be written costs nothing but the build."""

from __future__ import annotations

import os

import numpy as np
import pytest

from sim import diskcache, render, textures


@pytest.fixture
def cache_dir(tmp_path, monkeypatch):
    monkeypatch.setenv(diskcache.ENV_VAR, str(tmp_path / "cache"))
    return tmp_path / "cache"


def _counting_build(calls: list[int], value: float):
    def build():
        calls.append(1)
        return {"a": np.full((3, 4), value, np.float32)}, {"x": value, "n": [1, 2]}
    return build


def test_an_entry_is_built_once_and_read_back_as_built(cache_dir, tmp_path):
    src = tmp_path / "input.bin"
    src.write_bytes(b"12345")
    calls: list[int] = []
    key = diskcache.fingerprint(files=[src], modules=[textures], p=3)
    a1, m1 = diskcache.cached("t", key, _counting_build(calls, 1.5))
    a2, m2 = diskcache.cached("t", key, _counting_build(calls, 9.0))
    assert len(calls) == 1 and m1 == m2 == {"x": 1.5, "n": [1, 2]}
    assert np.array_equal(a1["a"], a2["a"]) and a2["a"].dtype == np.float32 and not a2["a"].flags.writeable
    # the input file changes: a new key, built again
    src.write_bytes(b"123456")
    _, m3 = diskcache.cached("t", diskcache.fingerprint(files=[src], modules=[textures], p=3),
                             _counting_build(calls, 2.5))
    assert len(calls) == 2 and m3["x"] == 2.5


def test_off_and_unwritable_caches_only_build(tmp_path, monkeypatch):
    calls: list[int] = []
    monkeypatch.setenv(diskcache.ENV_VAR, "off")
    for _ in range(2):
        diskcache.cached("t", {"k": 1}, _counting_build(calls, 1.0))
    assert len(calls) == 2
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    monkeypatch.setenv(diskcache.ENV_VAR, str(blocker / "cache"))
    a, _ = diskcache.cached("t", {"k": 1}, _counting_build(calls, 1.0))
    assert len(calls) == 3 and a["a"].shape == (3, 4)


def test_a_real_world_and_the_pixel_tables_from_the_cache_are_those_built(cache_dir, camera, monkeypatch):
    textures._world_by_name.cache_clear()
    monkeypatch.setenv(diskcache.ENV_VAR, "off")
    built = textures.GroundWorld.from_name("farmland")
    textures._world_by_name.cache_clear()
    monkeypatch.setenv(diskcache.ENV_VAR, str(cache_dir))
    first = textures.GroundWorld.from_name("farmland")      # builds and stores
    textures._world_by_name.cache_clear()
    again = textures.GroundWorld.from_name("farmland")      # reads
    textures._world_by_name.cache_clear()
    assert len(os.listdir(cache_dir / "world")) == 1
    for w in (first, again):
        assert np.array_equal(w.atlas, built.atlas) and np.array_equal(w.level_origin_px, built.level_origin_px)
        assert (w.name, w.m_per_px, w.tile_px, w.origin_px) == (built.name, built.m_per_px, built.tile_px,
                                                                 built.origin_px)
        assert not w.atlas.flags.writeable
    render._PIXEL_TABLES.clear()
    tables = render._pixel_tables(camera)
    render._PIXEL_TABLES.clear()
    ref = render._build_pixel_tables(camera)
    assert all(np.array_equal(a, b) for a, b in zip(tables, ref, strict=True))
    render._PIXEL_TABLES.clear()
