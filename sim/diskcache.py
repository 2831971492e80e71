"""A disk cache for the simulator's arrays that take seconds to build and are the same in every run: the real ground
tiles' mip atlases (:mod:`sim.textures`, about 1 s for the mosaic) and the renderer's per-pixel lens tables
(:mod:`sim.render`, about 0.3 s).  A ``gsoe sim`` run loads them in a few tens of milliseconds instead.

An entry is a folder of ``.npy`` arrays and a ``meta.json`` (the builder's scalars), named by a hash of its key:
what the arrays are made from (files by size and modification time, the building modules' source, the NumPy and
OpenCV versions, parameters).  Anything that changes them changes the key, so an entry is never stale; old entries
are simply left behind (delete the folder at will).  Entries are written to a temporary folder and renamed into
place, so concurrent workers never read a half-written one.

Where: ``$GSOE_CACHE_DIR``, else ``$XDG_CACHE_HOME/gsoe-nav``, else ``~/.cache/gsoe-nav``; ``GSOE_CACHE_DIR=off``
(or an empty value) turns the cache off.  A cache that cannot be read or written is skipped (the arrays are built),
never an error.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import tempfile
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from types import ModuleType
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

log = logging.getLogger(__name__)

ENV_VAR = "GSOE_CACHE_DIR"
_META = "meta.json"

Arrays = dict[str, NDArray[Any]]
Built = tuple[Arrays, dict[str, Any]]


def cache_root() -> Path | None:
    """The cache folder, or None when the cache is off."""
    env = os.environ.get(ENV_VAR)
    if env is not None:
        return None if env.strip() in ("", "off") else Path(env)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "gsoe-nav"


def fingerprint(*, files: Iterable[str | Path] = (), modules: Iterable[ModuleType] = (),
                **params: Any) -> dict[str, Any]:
    """A key for :func:`cached`: the files by size and modification time, the modules by their source's hash, the
    library versions, and ``params`` (JSON-able)."""
    fs = {}
    for f in files:
        st = os.stat(f)
        fs[str(f)] = [st.st_size, st.st_mtime_ns]
    ms = {m.__name__: hashlib.sha256(Path(str(m.__file__)).read_bytes()).hexdigest() for m in modules}
    return {"files": fs, "modules": ms, "numpy": np.__version__, "opencv": cv2.__version__, "params": params}


def cached(kind: str, key: Mapping[str, Any], build: Callable[[], Built]) -> Built:
    """The arrays and scalars ``build()`` returns, from the cache entry of ``key`` if there is one (arrays read-only),
    else built and stored."""
    root = cache_root()
    if root is None:
        return build()
    digest = hashlib.sha256(json.dumps(key, sort_keys=True, default=str).encode()).hexdigest()[:24]
    entry = root / kind / digest
    got = _load(entry)
    if got is not None:
        return got
    arrays, meta = build()
    _store(entry, arrays, meta)
    return arrays, meta


def _load(entry: Path) -> Built | None:
    try:
        meta = json.loads((entry / _META).read_text())
        arrays = {name: np.load(entry / f"{name}.npy", allow_pickle=False) for name in meta["arrays"]}
    except (OSError, ValueError, KeyError, TypeError):
        return None
    for a in arrays.values():
        a.setflags(write=False)
    log.debug("cache hit %s", entry)
    return arrays, meta["meta"]


def _store(entry: Path, arrays: Arrays, meta: dict[str, Any]) -> None:
    tmp: str | None = None
    try:
        entry.parent.mkdir(parents=True, exist_ok=True)
        tmp = tempfile.mkdtemp(prefix=".tmp-", dir=entry.parent)
        for name, a in arrays.items():
            np.save(Path(tmp) / f"{name}.npy", np.ascontiguousarray(a), allow_pickle=False)
        (Path(tmp) / _META).write_text(json.dumps({"arrays": list(arrays), "meta": meta}))
        os.rename(tmp, entry)            # atomic; fails if another process got there first (its entry stands)
        tmp = None
        log.debug("cache stored %s", entry)
    except OSError as e:
        log.debug("cache not written (%s): %s", entry, e)
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)


def cached_arrays(kind: str, key: Mapping[str, Any], build: Callable[[], tuple[NDArray[Any], ...]]
                  ) -> tuple[NDArray[Any], ...]:
    """A tuple of arrays through the cache (``key`` from :func:`fingerprint`)."""
    a, _ = cached(kind, key, lambda: ({f"a{i}": v for i, v in enumerate(build())}, {}))
    return tuple(a[f"a{i}"] for i in range(len(a)))
