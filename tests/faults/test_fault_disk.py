"""Disk full on the data folder and the robot link dropped mid-scan, against the real service (issue #13).

* The data folder is a 4 MiB tmpfs (``mount -t tmpfs``, root only; skipped otherwise), filled up with a
  ballast file: ``POST /register`` answers 507 problem details naming the full folder, the current
  registration and every stored row stay, and once space is freed the service registers again.
* The mock controller drops the link (and keeps it silent) while a scan is acquired: the scan is
  recorded as not still (link down / gap in the joint history), ``POST /register`` refuses it with
  the reason, and the link recovers (``/status`` connected again, the next scan registers).
* A burst of 10 scans arriving together is recorded completely (10 complete scans, one event each).
"""

from __future__ import annotations

import errno
import os
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from registration.model.frames import transform_from_xyz_rpy
from tests.faults._service import Events, Svc, factory_series, in_process_service, wait_for
from tests.helpers.scan_cache import simulated_scan

IMAGE_FROM_PHANTOM = transform_from_xyz_rpy([2.0, -3.0, 1.0], [10.0, -6.0, 20.0])
TMPFS_SIZE = "4m"


@pytest.fixture(scope="module")
def small_scan(phantom: Any) -> Any:
    from mocks.oarm.simulator import AcquisitionSettings

    return simulated_scan(phantom, IMAGE_FROM_PHANTOM, AcquisitionSettings.preset("small"))


def _export(svc: Svc, scan: Any, name: str) -> str:
    from mocks.oarm.dicom_export import write_dicom_series

    staging = svc.watch.parent / f"staging-{name}"
    uid = str(write_dicom_series(scan, staging, write_truth=False).series_uid)
    os.replace(staging, svc.watch / name)
    return uid


@pytest.fixture
def tmpfs_root(tmp_path: Path) -> Iterator[Path]:
    mnt = tmp_path / "data"
    mnt.mkdir()
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    r = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={TMPFS_SIZE}", "tmpfs", str(mnt)], capture_output=True
    )
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.decode(errors='replace').strip()}")
    try:
        yield tmp_path
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)


def _fill(folder: Path) -> Path:
    """Write a ballast file until the file system is full (ENOSPC)."""
    ballast = folder / "ballast.bin"
    chunk = b"\0" * 65536
    with ballast.open("wb") as f:
        try:
            while True:
                f.write(chunk)
                f.flush()
        except OSError as e:
            assert e.errno == errno.ENOSPC, e
    return ballast


def test_disk_full_on_the_data_folder_is_507_and_loses_nothing(
    tmpfs_root: Path, phantom: Any, small_scan: Any
) -> None:
    from registration.model.kinematics import RobotModel

    loose = {"stillness.window_s": 1.2, "stillness.max_gap_s": 0.6}
    with in_process_service(tmpfs_root, phantom, RobotModel.load("tx60"), **loose) as svc:
        svc.wait_still()
        uid = _export(svc, small_scan, "scan-disk")
        scan = svc.scan_where(lambda s: s["series_uid"] == uid, "the scan recorded")
        first = svc.client.post("/register", json={"scan_id": scan["id"]})
        assert first.status_code == 200, first.text
        before = svc.client.get("/registrations").json()
        ballast = _fill(svc.data)
        try:
            r = svc.client.post("/register", json={"scan_id": scan["id"]})
            assert r.status_code == 507, r.text
            assert r.headers["content-type"].startswith("application/problem+json")
            body = r.json()
            assert body["title"] == "Data folder full" and str(svc.data) in body["detail"], body
            cur = svc.client.get("/registration/current")
            assert cur.status_code == 200 and cur.json()["id"] == first.json()["id"]
            assert svc.client.get("/registrations").json() == before  # nothing lost, nothing half-written
        finally:
            ballast.unlink()
        again = svc.client.post("/register", json={"scan_id": scan["id"]})
        assert again.status_code == 200 and again.json()["is_current"], again.text


def test_link_dropped_mid_scan_is_refused_with_the_reason_and_recovers(
    tmp_path: Path, phantom: Any, small_scan: Any
) -> None:
    from registration.model.kinematics import RobotModel

    loose = {"stillness.window_s": 1.2, "stillness.max_gap_s": 0.3}
    with in_process_service(tmp_path, phantom, RobotModel.load("tx60"), **loose) as svc:
        svc.wait_still()
        # the link drops while the O-arm acquires, and stays silent (no frames after the reconnect)
        # until the scan is recorded: the joint snapshot surely covers the outage
        svc.mock.stall()
        svc.mock.disconnect(down_s=0.3)
        try:
            uid = _export(svc, small_scan, "scan-drop")
            scan = svc.scan_where(lambda s: s["series_uid"] == uid, "the scan recorded")
        finally:
            svc.mock.resume()
        assert scan["joints"]["still"] is False, scan["joints"]
        r = svc.client.post("/register", json={"scan_id": scan["id"]})
        assert r.status_code == 409, r.text
        detail = r.json()["detail"].lower()
        assert "link" in detail or "gap" in detail or "stillness" in detail, detail
        wait_for(lambda: svc.client.get("/status").json()["link"]["state"] == "connected", "the link back")
        svc.wait_still()
        uid2 = _export(svc, small_scan, "scan-after")  # same voxels, a new series UID
        after = svc.scan_where(lambda s: s["series_uid"] == uid2, "the next scan")
        assert after["joints"]["still"] is True, after["joints"]
        ok = svc.client.post("/register", json={"scan_id": after["id"]})
        assert ok.status_code == 200, ok.text


def test_a_burst_of_ten_scans_is_recorded_completely(tmp_path: Path, phantom: Any) -> None:
    from registration.model.kinematics import RobotModel

    with in_process_service(tmp_path, phantom, RobotModel.load("tx60")) as svc:
        staging = tmp_path / "burst"
        uids = [f"1.2.826.0.1.13.10.{k}" for k in range(10)]
        for k, uid in enumerate(uids):
            factory_series(staging / f"s{k}", n=6, series_uid=uid)
        with Events(svc) as events:
            for k in range(10):
                shutil.move(str(staging / f"s{k}"), str(svc.watch / f"burst-{k}"))
            pending = set(uids)
            while pending:
                pending.discard(
                    events.wait("scan_arrived", lambda d: d["series_uid"] in pending)["series_uid"]
                )
        by_uid = {s["series_uid"]: s for s in svc.scans()}
        assert all(by_uid[u]["status"] == "complete" and by_uid[u]["n_slices"] == 6 for u in uids)
        assert svc.client.get("/status").json()["watcher"]["health"] == "ok"
