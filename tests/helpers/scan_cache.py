"""One simulation per distinct scan per test run, shared by the xdist workers.

Many modules (faults, integration, browser) feed the service the same ``small`` scan at the same
pose; each simulation costs ~1.4 s of CPU, and CI's two cores are shared with other jobs, so the
suite paid for one scan 17 times (measured with a per-call log over a full run: 24 s of CPU).
:func:`simulated_scan` computes a scan once per run and hands every later caller a fresh copy
(unpickled: mutating it changes nobody else's).

The cache lives only for one run: a new folder the controller names in an environment variable
before xdist starts its workers (they inherit it) and removes at the end
(:func:`remove_run_cache`).  Nothing is read from an earlier run, so a change to the simulator can
never be hidden by a stale scan.  The key
is the SHA-256 of the pickled inputs (phantom, pose, settings, extras).
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import pickle
import shutil
import tempfile
import uuid
from pathlib import Path
from typing import Any

import numpy as np

from mocks.oarm.simulator import AcquisitionSettings, SceneExtras, SimulatedScan, simulate_scan
from registration.model.phantom import Phantom

RUN_ENV = "TESTS_SCAN_CACHE_DIR"
"""The environment variable naming this run's cache folder (set by :func:`init_run_cache`); not
``OARMREG_``-prefixed: the service refuses unknown variables of its own prefix."""


def init_run_cache() -> Path:
    """Name a new cache folder for this run (not created until a scan is stored)."""
    folder = Path(tempfile.gettempdir()) / f"oarmreg-scan-cache-{uuid.uuid4().hex}"
    os.environ[RUN_ENV] = str(folder)
    return folder


def remove_run_cache() -> None:
    """Remove this run's cache folder (the controller, once every worker is done)."""
    folder = os.environ.get(RUN_ENV)
    if folder:
        shutil.rmtree(folder, ignore_errors=True)


def _key(
    phantom: Phantom, image_from_phantom: Any, settings: AcquisitionSettings, extras: SceneExtras
) -> str:
    pose = np.ascontiguousarray(image_from_phantom, dtype=np.float64).tobytes()
    return hashlib.sha256(pickle.dumps((phantom, pose, settings, extras), protocol=5)).hexdigest()


def simulated_scan(
    phantom: Phantom,
    image_from_phantom: Any,
    settings: AcquisitionSettings,
    extras: SceneExtras | None = None,
) -> SimulatedScan:
    """:func:`mocks.oarm.simulator.simulate_scan`, computed once per run for the same inputs."""
    extras = SceneExtras() if extras is None else extras
    folder = os.environ.get(RUN_ENV)
    if not folder:  # outside pytest (a helper run by hand): no cache
        return simulate_scan(phantom, image_from_phantom, settings, extras)
    path = Path(folder) / f"{_key(phantom, image_from_phantom, settings, extras)}.pickle"
    cached = _load(path)
    if cached is not None:
        return cached
    path.parent.mkdir(parents=True, exist_ok=True)
    # One simulation per key: a second worker asking for the same scan meanwhile waits on the lock
    # and reads the first one's file (without it, one full run simulated two of its scans twice).
    with path.with_name(f"{path.name}.lock").open("wb") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        cached = _load(path)
        if cached is not None:
            return cached
        scan = simulate_scan(phantom, image_from_phantom, settings, extras)
        part = path.with_name(f"{path.name}.{uuid.uuid4().hex}.part")
        with part.open("wb") as f:
            pickle.dump(scan, f, protocol=5)
        os.replace(part, path)
    return scan


def _load(path: Path) -> SimulatedScan | None:
    """The cached scan at ``path`` (a fresh copy), or None if none is stored yet."""
    try:
        with path.open("rb") as f:
            cached = pickle.load(f)
    except FileNotFoundError:
        return None
    assert isinstance(cached, SimulatedScan)
    return cached
