"""Issue #13 items 1, 3 and 8 against the real service over loopback (mock controller, uvicorn thread).

1. A FIFO (and other hostile entries) in the watch folder never stops the watcher; ``/status`` tells the
   truth about it; ``detect`` on a FIFO refuses with exit code 4 (input data), on ``/dev`` refuses
   without opening a device.
3. An export that pauses longer than the quiet period: the late slices reopen the recorded scan and the
   registration made from the short version is withdrawn (no longer current, SSE event with the reason);
   a series announcing its slice count (ImagesInAcquisition) is not taken as complete before.
8. Folders with no readable series (NUL files, link loops, a DICOMDIR pointing outside) are recorded in
   ``/scans`` as invalid with the reason and a ``scan_invalid`` event.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from registration.model.frames import transform_from_xyz_rpy
from tests.faults._service import DEADLINE_S, Events, Svc, factory_series, in_process_service, wait_for
from tests.helpers.scan_cache import simulated_scan

IMAGE_FROM_PHANTOM = transform_from_xyz_rpy([2.0, -3.0, 1.0], [10.0, -6.0, 20.0])


@pytest.fixture(scope="module")
def svc(tmp_path_factory: pytest.TempPathFactory, phantom: Any) -> Iterator[Svc]:
    from registration.model.kinematics import RobotModel

    # a wider gap tolerance than the default test settings: the suite shares 2 cores with the others
    root = tmp_path_factory.mktemp("faults-files")
    loose = {"stillness.window_s": 1.2, "stillness.max_gap_s": 0.6}
    with in_process_service(root, phantom, RobotModel.load("tx60"), **loose) as s:
        s.wait_still()
        yield s


@pytest.fixture(scope="module")
def small_scan(phantom: Any) -> Any:
    from mocks.oarm.simulator import AcquisitionSettings

    return simulated_scan(phantom, IMAGE_FROM_PHANTOM, AcquisitionSettings.preset("small"))


def _status_watcher(svc: Svc) -> dict[str, Any]:
    return svc.client.get("/status").json()["watcher"]  # type: ignore[no-any-return]


# ---------------------------------------------------------------------------------------- item 1


def test_fifo_in_the_watch_folder_never_stops_the_watcher(svc: Svc, tmp_path: Path) -> None:
    x = svc.watch / f"fifo-{tmp_path.name}"
    x.mkdir(parents=True)
    os.mkfifo(x / "CT.dcm")  # opening it for reading blocks until a writer comes: nobody will
    staging = tmp_path / "staging"
    paths = factory_series(staging / "x", n=6, series_uid="1.2.826.0.1.13.1")
    for p in paths:
        os.replace(p, x / p.name)
    other = factory_series(staging / "y", n=6, series_uid="1.2.826.0.1.13.2")
    shutil.move(str(other[0].parent), str(svc.watch / f"after-fifo-{tmp_path.name}"))
    for uid in ("1.2.826.0.1.13.1", "1.2.826.0.1.13.2"):  # both recorded: the FIFO did not block anything
        scan = svc.scan_where(lambda s, u=uid: s["series_uid"] == u, f"series {uid} recorded")
        assert scan["status"] == "complete" and scan["n_slices"] == 6, scan
    w = _status_watcher(svc)
    assert w["running"] is True and w["health"] == "ok", w


def test_detect_refuses_a_fifo_and_dev_without_opening_them(tmp_path: Path) -> None:
    from service.cli.main import main

    fifo = tmp_path / "CT.dcm"
    os.mkfifo(fifo)
    assert main(["detect", str(fifo)]) == 4  # EXIT_INPUT, not a traceback and not a hang
    assert main(["detect", "/dev"]) == 4  # every device skipped unopened: no CT series


def test_watcher_health_is_stopped_when_its_thread_is_gone(tmp_path: Path) -> None:
    from service.intake.watcher import SeriesWatcher

    w = SeriesWatcher(tmp_path / "w", on_series=lambda a: None, use_polling_only=True)
    assert w.state()["health"] == "stopped" and w.state()["running"] is False
    w.start()
    try:
        assert wait_for(lambda: w.state()["health"] == "ok", "watcher healthy")
    finally:
        w.stop()
    assert w.state()["health"] == "stopped"


def test_watcher_reports_stalled_while_one_folder_blocks_it(tmp_path: Path) -> None:
    import threading

    from service.intake.watcher import SeriesWatcher

    release = threading.Event()
    entered = threading.Event()

    def slow(arrival: Any) -> None:  # a recording that hangs (a blocked read on a network share, say)
        entered.set()
        release.wait(DEADLINE_S)

    w = SeriesWatcher(
        tmp_path / "w", on_series=slow, use_polling_only=True, quiet_period_s=0.05, poll_interval_s=0.05,
        stall_after_s=0.2,
    )  # fmt: skip
    w.start()
    try:
        factory_series(tmp_path / "w" / "s", n=3)
        assert entered.wait(DEADLINE_S)
        st = wait_for(lambda: (s := w.state())["health"] == "stalled" and s, "health stalled")
        assert st["running"] is False and str(tmp_path / "w" / "s") in st["busy_folder"]
        assert "processing" in st["health_reason"]
    finally:
        release.set()
        w.stop()


# ---------------------------------------------------------------------------------------- item 8


def _dicomdir_pointing_outside(tmp_path: Path, folder: Path) -> None:
    """A DICOMDIR whose image directory is a link to a series outside the folder."""
    from pydicom import dcmread
    from pydicom.fileset import FileSet

    source = tmp_path / "outside"
    paths = factory_series(source / "src", n=4)
    fs = FileSet()
    for p in paths:
        fs.add(dcmread(p))
    fs.write(source / "media")
    folder.mkdir(parents=True)
    shutil.copy(source / "media" / "DICOMDIR", folder / "DICOMDIR")
    for entry in (source / "media").iterdir():
        if entry.name != "DICOMDIR":
            os.symlink(entry, folder / entry.name)  # the references resolve outside the folder


def test_folders_without_a_readable_series_are_recorded_invalid(svc: Svc, tmp_path: Path) -> None:
    staging = tmp_path / "staging"
    builders = {
        "nul": lambda d: [(d / f"IM{k}.dcm").write_bytes(b"\0" * 2048) for k in range(3)],
        "loop": lambda d: [os.symlink("a.dcm", d / "a.dcm"), (d / "notes.txt").write_text("x")],
        "fifo-only": lambda d: os.mkfifo(d / "CT0001.dcm"),
    }
    expected: dict[Path, str] = {}
    with Events(svc) as events:
        for name, build in builders.items():
            d = staging / name
            d.mkdir(parents=True)
            build(d)
            target = svc.watch / f"{name}-{tmp_path.name}"
            os.replace(d, target)
            expected[target] = name
        dicomdir = svc.watch / f"dicomdir-{tmp_path.name}"
        _dicomdir_pointing_outside(tmp_path, staging / "dd")
        os.replace(staging / "dd", dicomdir)
        expected[dicomdir] = "dicomdir"
        pending = {f"folder:{p}" for p in expected}
        while pending:
            data = events.wait("scan_invalid", lambda d: d["series_uid"] in pending)
            pending.discard(data["series_uid"])
            assert data["reason"] and data["scan_id"]
    by_uid = {s["series_uid"]: s for s in svc.scans()}
    for folder in expected:
        scan = by_uid[f"folder:{folder}"]
        assert scan["status"] == "invalid" and scan["folder"] == str(folder), scan
    assert "no readable CT series" in by_uid[f"folder:{svc.watch / f'nul-{tmp_path.name}'}"]["reason"]
    assert "ELOOP" in by_uid[f"folder:{svc.watch / f'loop-{tmp_path.name}'}"]["reason"]
    assert "FIFO" in by_uid[f"folder:{svc.watch / f'fifo-only-{tmp_path.name}'}"]["reason"]
    dd_reason = by_uid[f"folder:{dicomdir}"]["reason"]  # pydicom's File-set check or ours: refused either way
    assert "outside" in dd_reason or "inside the DICOMDIR root" in dd_reason, dd_reason
    assert _status_watcher(svc)["health"] == "ok"


# ---------------------------------------------------------------------------------------- item 3


def test_announced_slice_count_keeps_a_paused_export_from_being_complete(svc: Svc, tmp_path: Path) -> None:
    uid = "1.2.826.0.1.13.3"
    paths = factory_series(
        tmp_path / "s", n=8, series_uid=uid, overrides={k: {"ImagesInAcquisition": 8} for k in range(8)}
    )
    target = svc.watch / f"announced-{tmp_path.name}"
    target.mkdir()
    for p in paths[:5]:  # the export pauses after 5 of 8 slices, longer than the quiet period
        os.replace(p, target / p.name)
    first = svc.scan_where(lambda s: s["series_uid"] == uid, "the paused series recorded")
    assert first["status"] == "invalid" and "5 slices found" in first["reason"] and "8" in first["reason"]
    for p in paths[5:]:
        os.replace(p, target / p.name)
    done = svc.scan_where(
        lambda s: s["series_uid"] == uid and s["status"] == "complete", "the completed series"
    )
    assert done["id"] == first["id"] and done["n_slices"] == 8


def test_late_slices_reopen_the_scan_and_withdraw_its_registration(
    svc: Svc, small_scan: Any, tmp_path: Path
) -> None:
    from mocks.oarm.dicom_export import write_dicom_series

    staging = tmp_path / "staging"
    uid = str(write_dicom_series(small_scan, staging, write_truth=False).series_uid)
    files = sorted(staging.glob("*.dcm"))
    n_late = len(files) // 6  # the export pauses with the last sixth of the slices still to come
    target = svc.watch / f"paused-{tmp_path.name}"
    target.mkdir()
    for p in files[:-n_late]:
        os.replace(p, target / p.name)
    short = svc.scan_where(lambda s: s["series_uid"] == uid, "the short version recorded")
    assert short["status"] == "complete" and short["n_slices"] == len(files) - n_late
    svc.wait_still()
    r = svc.client.post("/register", json={"scan_id": short["id"]})
    assert r.status_code == 200, r.text
    reg = r.json()
    assert svc.client.get("/registration/current").json()["id"] == reg["id"]

    with Events(svc) as events:
        for p in files[-n_late:]:  # the rest of the export arrives
            os.replace(p, target / p.name)
        reopened = events.wait("scan_reopened", lambda d: d["series_uid"] == uid)
        withdrawn = events.wait("registration_withdrawn", lambda d: reg["id"] in d["registration_ids"])
    assert reopened["previous_slices"] == len(files) - n_late and reopened["n_slices"] == len(files)
    assert withdrawn["was_current"] is True and "incomplete" in withdrawn["reason"]
    cur = svc.client.get("/registration/current")
    assert cur.status_code == 409 and "withdrawn" in cur.json()["detail"], cur.text
    assert svc.client.get("/status").json()["current_registration"] is None
    rec = svc.client.get(f"/registrations/{reg['id']}").json()
    assert rec["status"] == "withdrawn" and rec["is_current"] is False and "incomplete" in rec["reason"]
    full = svc.client.get(f"/scans/{short['id']}").json()
    assert full["status"] == "complete" and full["n_slices"] == len(files)
    r2 = svc.client.post("/register", json={"scan_id": short["id"]})  # the completed scan registers again
    assert r2.status_code == 200 and r2.json()["is_current"], r2.text


@pytest.mark.parametrize("kind", ["fifo", "folder", "device"])
def test_a_phantom_file_that_is_not_a_regular_file_is_refused_unread(tmp_path: Path, kind: str) -> None:
    """``--phantom`` (and the service's ``phantom_file``) pointed at a FIFO, a folder or a device:
    a configuration error naming what it is, exit 3, never a hang on the FIFO or a traceback."""
    import threading

    from registration.errors import PhantomDefinitionError
    from registration.model.phantom import load_phantom
    from service.cli.main import main
    from service.error_map import EXIT_CONFIG

    path = {"fifo": tmp_path / "phantom.toml", "folder": tmp_path, "device": Path("/dev/zero")}[kind]
    if kind == "fifo":
        os.mkfifo(path)
    outcome: list[BaseException | None] = []

    def attempt() -> None:
        try:
            load_phantom(path)
            outcome.append(None)
        except BaseException as e:
            outcome.append(e)

    t = threading.Thread(target=attempt, daemon=True)
    t.start()
    t.join(DEADLINE_S)
    if t.is_alive():  # blocked opening the FIFO: release it so the thread ends, then fail
        with open(path, "w"):
            pass
        pytest.fail(f"load_phantom blocked on {kind} {path}")
    assert isinstance(outcome[0], PhantomDefinitionError), outcome
    assert "not a regular file" in str(outcome[0]) and str(path) in str(outcome[0])
    assert main(["detect", str(tmp_path), "--phantom", str(path)]) == EXIT_CONFIG
