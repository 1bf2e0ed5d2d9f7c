"""The per-run simulated-scan cache (tests/helpers/scan_cache.py): computed once, copies handed out."""

from __future__ import annotations

import fcntl
import pickle
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mocks.oarm.simulator import AcquisitionSettings, SceneExtras
from registration.model.frames import transform_from_xyz_rpy
from tests.helpers import scan_cache
from tests.integration.polling import poll_until

TINY = {"rows": 48, "columns": 48, "n_slices": 6, "n_views": 40}
"""A scan small enough to simulate in a fraction of a second."""


def test_one_simulation_per_distinct_scan_and_every_caller_gets_its_own_copy(
    phantom: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(scan_cache.RUN_ENV, str(tmp_path / "cache"))
    calls: list[int] = []
    real = scan_cache.simulate_scan

    def counted(*args: Any) -> Any:
        calls.append(1)
        return real(*args)

    monkeypatch.setattr(scan_cache, "simulate_scan", counted)
    pose = transform_from_xyz_rpy([2.0, -3.0, 1.0], [10.0, -6.0, 20.0])
    s = AcquisitionSettings.preset("small", **TINY)
    a = scan_cache.simulated_scan(phantom, pose, s)
    b = scan_cache.simulated_scan(phantom, pose.copy(), AcquisitionSettings.preset("small", **TINY))
    assert len(calls) == 1
    assert np.array_equal(a.hu, b.hu) and np.array_equal(a.spheres_image_mm, b.spheres_image_mm)
    b.hu[...] = 0  # a caller's change reaches nobody else
    assert not np.array_equal(scan_cache.simulated_scan(phantom, pose, s).hu, b.hu)
    # any input that differs is another scan
    scan_cache.simulated_scan(phantom, pose, AcquisitionSettings.preset("small", **TINY, seed=1))
    scan_cache.simulated_scan(phantom, pose, s, SceneExtras(sphere_material="plastic"))
    moved = transform_from_xyz_rpy([2.0, -3.0, 1.001], [10.0, -6.0, 20.0])
    scan_cache.simulated_scan(phantom, moved, s)
    assert len(calls) == 4


def test_without_a_run_folder_nothing_is_cached(phantom: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(scan_cache.RUN_ENV, raising=False)
    calls: list[int] = []
    real = scan_cache.simulate_scan
    monkeypatch.setattr(scan_cache, "simulate_scan", lambda *a: calls.append(1) or real(*a))
    pose = transform_from_xyz_rpy([0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    s = AcquisitionSettings.preset("small", **TINY)
    scan_cache.simulated_scan(phantom, pose, s)
    scan_cache.simulated_scan(phantom, pose, s)
    assert len(calls) == 2


def _waiting_on(lock_path: Path) -> bool:
    """Someone waits for the flock on ``lock_path`` (Linux ``/proc/locks``: a waiter line has "->")."""
    ino = f":{lock_path.stat().st_ino} "
    return any("->" in line and ino in line for line in Path("/proc/locks").read_text().splitlines())


def test_a_second_caller_waits_for_the_simulation_under_way_instead_of_repeating_it(
    phantom: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two workers asking for the same scan at once: the second waits for the first one's file."""
    folder = tmp_path / "cache"
    monkeypatch.setenv(scan_cache.RUN_ENV, str(folder))
    pose = transform_from_xyz_rpy([2.0, -3.0, 1.0], [10.0, -6.0, 20.0])
    s = AcquisitionSettings.preset("small", **TINY)
    real = scan_cache.simulate_scan
    first = real(phantom, pose, s, SceneExtras())
    calls: list[int] = []
    monkeypatch.setattr(scan_cache, "simulate_scan", lambda *a: calls.append(1) or real(*a))
    path = folder / f"{scan_cache._key(phantom, pose, s, SceneExtras())}.pickle"
    folder.mkdir()
    got: list[Any] = []
    with path.with_name(f"{path.name}.lock").open("wb") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # the first worker, simulating
        second = threading.Thread(target=lambda: got.append(scan_cache.simulated_scan(phantom, pose, s)))
        second.start()
        poll_until(lambda: _waiting_on(Path(lock.name)), "the second caller on the lock", 10.0)
        with path.open("wb") as f:  # the first worker's result lands, then its lock is released
            pickle.dump(first, f, protocol=5)
    second.join(10.0)
    assert calls == [] and len(got) == 1
    assert np.array_equal(got[0].hu, first.hu)
