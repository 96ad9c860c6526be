"""Memory and per-user disk cache of calibrations (formulations/substrate.md, sec. 7).

A calibration depends only on (shape, tiling, gap, nu, refinement, calibration rings, cross
terms) and the code version of the boundary-element model (``BEM_VERSION``); the key hashes
exactly these.  The disk cache lives in the per-user cache directory (platformdirs) or in
``$QPSCALE_CACHE_DIR``; ``QPSCALE_CACHE_DIR=off`` disables it.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import zipfile
from pathlib import Path

import numpy as np

from .calibration import Calibration, Coupling

log = logging.getLogger(__name__)

# Bump when the discretisation changes so that stale calibrations are never reused.
BEM_VERSION = 2
_MEMORY: dict[str, Calibration] = {}


def cache_key(**params: object) -> str:
    text = json.dumps({"bem_version": BEM_VERSION, **params}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:24]


def cache_dir() -> Path | None:
    env = os.environ.get("QPSCALE_CACHE_DIR")
    if env == "off":
        return None
    if env:
        return Path(env)
    from platformdirs import user_cache_dir

    return Path(user_cache_dir("qpscale")) / "substrate"


def _save(path: Path, cal: Calibration) -> None:
    cp = cal.couplings
    arrays = {
        "K_iso": cal.K_iso,
        "K0": cal.K0,
        "scalars": np.array([cal.asymmetry, cal.n_panels, cal.wall_s]),
        "ints": np.array([[c.source, c.receiver, *c.site] for c in cp], dtype=int).reshape(-1, 4),
        "offsets": np.array([c.offset for c in cp]).reshape(-1, 2),
        "K1": np.array([c.K1 for c in cp]).reshape(-1, 5, 5),
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    # Written whole to a temporary file, then renamed: a reader never sees a truncated file under
    # the final name, and an interrupted or failed write (disk full) leaves no file behind.
    tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")
    try:
        np.savez(tmp, **arrays)  # type: ignore[arg-type]  # numpy's stub types **kwds as allow_pickle
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _load(path: Path) -> Calibration:
    with np.load(path) as z:
        cp = tuple(
            Coupling(int(i[0]), int(i[1]), (int(i[2]), int(i[3])), (float(o[0]), float(o[1])), k)
            for i, o, k in zip(z["ints"], z["offsets"], z["K1"])
        )
        s = z["scalars"]
        return Calibration(z["K_iso"], z["K0"], cp, float(s[0]), int(s[1]), float(s[2]))


def cached(key: str, compute) -> Calibration:
    """Return the calibration stored under ``key``, computing and storing it if absent."""
    if key in _MEMORY:
        return _MEMORY[key]
    folder = cache_dir()
    path = folder / f"{key}.npz" if folder is not None else None
    cal = None
    if path is not None and path.exists():
        try:
            cal = _load(path)
        except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile) as exc:
            # A truncated or corrupt file (an older version's interrupted write) is recomputed and
            # replaced below, never fatal.
            log.warning("ignoring unreadable substrate cache %s: %s", path, exc)
    if cal is None:
        cal = compute()
        if path is not None:
            try:
                _save(path, cal)
            except OSError as exc:
                log.warning("cannot write substrate cache %s: %s", path, exc)
    _MEMORY[key] = cal
    return cal


def clear_memory() -> None:
    _MEMORY.clear()
