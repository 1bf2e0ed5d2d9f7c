"""service/intake/watcher.py on tiny pydicom-written series, driven tick by tick (no thread, no sleeps),
plus one run of the real thread with OS events."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from service.intake.recording import SeriesArrival
from service.intake.watcher import SeriesWatcher, snapshot_dir
from tests.helpers.dicom_factory import ramp_volume, write_series

QUIET_S = 1.0


class Sink:
    def __init__(self) -> None:
        self.arrivals: list[SeriesArrival] = []
        self.known: set[str] = set()
        self.event = threading.Event()

    def __call__(self, a: SeriesArrival) -> None:
        self.arrivals.append(a)
        if not a.error and not a.duplicate:
            self.known.add(a.series_uid)
        self.event.set()


def make(tmp_path: Path, *, first_tick: bool = True) -> tuple[SeriesWatcher, Sink, Path]:
    watch = tmp_path / "watch"
    watch.mkdir()
    sink = Sink()
    w = SeriesWatcher(watch, on_series=sink, is_known=lambda uid: uid in sink.known, quiet_period_s=QUIET_S)
    if first_tick:
        w.tick(0.0)  # the start-up pass: empty folder
    return w, sink, watch


def series(folder: Path, n: int = 6, **kw: Any) -> list[Path]:
    return write_series(folder, ramp_volume(n, 8, 8), **kw)


def test_complete_after_quiet_period_only(tmp_path: Path) -> None:
    w, sink, watch = make(tmp_path)
    series(watch / "s1", series_uid="1.2.3.1")
    assert w.tick(10.0) == pytest.approx(10.0 + QUIET_S)  # first seen: due at the end of the quiet period
    assert w.tick(10.5) is not None and sink.arrivals == []
    w.tick(11.1)
    [a] = sink.arrivals
    assert a.series_uid == "1.2.3.1" and not a.error and not a.preexisting and a.n_files == 6
    assert a.volume.shape == (6, 8, 8) and a.first_seen_t_s == 10.0 and a.last_change_t_s == 10.0
    w.tick(20.0)
    assert len(sink.arrivals) == 1  # processed once


def test_change_restarts_quiet_period(tmp_path: Path) -> None:
    w, sink, watch = make(tmp_path)
    paths = series(watch / "s1", series_uid="1.2.3.2")
    w.tick(10.0)
    paths[-1].unlink()  # still being written / rewritten
    w.tick(10.8)
    w.tick(11.2)
    assert sink.arrivals == []
    w.tick(11.9)
    assert len(sink.arrivals) == 1 and sink.arrivals[0].last_change_t_s == 10.8


def test_part_files_are_ignored_but_block_stability(tmp_path: Path) -> None:
    w, sink, watch = make(tmp_path)
    d = watch / "s1"
    series(d, series_uid="1.2.3.3")
    part = d / ".IM0006.dcm.part"
    part.write_bytes(b"\x00" * 10)
    w.tick(10.0)
    part.write_bytes(b"\x00" * 20)  # the exporter is still writing
    w.tick(10.9)
    w.tick(11.5)
    assert sink.arrivals == []
    w.tick(12.0)
    [a] = sink.arrivals
    assert not a.error and a.volume.shape[0] == 6  # the .part file is not part of the series
    only_part = watch / "s2"
    only_part.mkdir()
    (only_part / ".x.dcm.part").write_bytes(b"1")
    w.tick(20.0)
    w.tick(30.0)
    assert len(sink.arrivals) == 1 and w.stats.junk_folders == 0


def test_several_series_at_once(tmp_path: Path) -> None:
    w, sink, watch = make(tmp_path)
    series(watch / "a", series_uid="1.2.3.10")
    series(watch / "b", series_uid="1.2.3.11", n=4)
    both = watch / "c"
    series(both, series_uid="1.2.3.12", n=5, name_format="A{:04d}.dcm")
    series(both, series_uid="1.2.3.13", n=3, name_format="B{:04d}.dcm")
    w.tick(10.0)
    w.tick(11.5)
    got = {a.series_uid: a.volume.shape[0] for a in sink.arrivals}
    assert got == {"1.2.3.10": 6, "1.2.3.11": 4, "1.2.3.12": 5, "1.2.3.13": 3}


def test_reexport_of_same_uid_is_a_duplicate(tmp_path: Path) -> None:
    w, sink, watch = make(tmp_path)
    series(watch / "first", series_uid="1.2.3.20")
    w.tick(10.0)
    w.tick(11.5)
    series(watch / "again", series_uid="1.2.3.20")
    w.tick(20.0)
    w.tick(21.5)
    assert [(a.series_uid, a.duplicate, a.volume is None) for a in sink.arrivals] == [
        ("1.2.3.20", False, False),
        ("1.2.3.20", True, True),
    ]
    assert w.state()["duplicates"] == 1


def test_junk_folder_is_reported_invalid(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    # issue #13 item 8: a folder with no readable series is recorded (invalid, with the reason)
    w, sink, watch = make(tmp_path)
    j = watch / "junk"
    j.mkdir()
    (j / "readme.txt").write_text("hello")
    (j / "broken.dcm").write_bytes(b"DICM" * 10)
    series(watch / "good", series_uid="1.2.3.30")
    (watch / "good" / "thumbs.db").write_bytes(b"\x01\x02")
    with caplog.at_level("INFO", logger="service.intake.watcher"):
        w.tick(10.0)
        w.tick(11.5)
    by_uid = {a.series_uid: a for a in sink.arrivals}
    assert set(by_uid) == {"1.2.3.30", f"folder:{j}"} and not by_uid["1.2.3.30"].error
    junk = by_uid[f"folder:{j}"]
    assert "no readable CT series" in junk.error and "broken.dcm" in junk.error and junk.volume is None
    assert w.stats.junk_folders == 1 and "junk" in caplog.text


def test_inconsistent_series_is_reported_invalid(tmp_path: Path) -> None:
    w, sink, watch = make(tmp_path)
    paths = series(watch / "gap", series_uid="1.2.3.40", n=8)
    paths[3].unlink()  # a missing slice: uneven spacing
    w.tick(10.0)
    w.tick(11.5)
    [a] = sink.arrivals
    assert a.error and a.volume is None and a.series_uid == "1.2.3.40"


def test_file_vanishing_while_loading_is_retried(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import registration.dicom as ds

    w, sink, watch = make(tmp_path)
    paths = series(watch / "s", series_uid="1.2.3.50", n=8)
    real = ds.load_series
    calls = []

    def vanishing(path: Any, **kw: Any) -> Any:
        calls.append(path)
        if len(calls) == 1:
            paths[4].unlink()  # the exporter replaces a file while we read
            raise FileNotFoundError(str(paths[4]))
        return real(path, **kw)

    monkeypatch.setattr(ds, "load_series", vanishing)
    w.tick(10.0)
    w.tick(11.5)
    assert sink.arrivals == [] and w.stats.retries == 1  # nothing recorded from a half-read folder
    series(watch / "s", series_uid="1.2.3.50", n=8)  # the file is back (re-written)
    import time

    now = time.monotonic()
    w.tick(now)
    w.tick(now + QUIET_S + 0.1)
    [a] = sink.arrivals
    assert not a.error and a.volume.shape[0] == 8 and len(calls) == 2


def test_series_present_at_start_are_flagged_preexisting(tmp_path: Path) -> None:
    w, sink, watch = make(tmp_path, first_tick=False)
    series(watch / "old", series_uid="1.2.3.60")
    w.tick(0.0)
    w.tick(1.5)
    [a] = sink.arrivals
    assert a.preexisting


def test_callback_failure_is_retried(tmp_path: Path) -> None:
    w, sink, watch = make(tmp_path)
    fails = [True]

    def flaky(a: SeriesArrival) -> None:
        if fails.pop(0) if fails else False:
            raise RuntimeError("database locked")
        sink(a)

    w.on_series = flaky
    series(watch / "s", series_uid="1.2.3.70")
    w.tick(10.0)
    w.tick(11.5)
    assert sink.arrivals == [] and "database locked" in w.state()["last_error"]
    import time

    now = time.monotonic()
    w.tick(now + QUIET_S + 0.1)
    assert [a.series_uid for a in sink.arrivals] == ["1.2.3.70"]


def test_snapshot_dir_counts_visible_files_only(tmp_path: Path) -> None:
    (tmp_path / "a.dcm").write_bytes(b"1")
    (tmp_path / ".a.dcm.part").write_bytes(b"12")
    snap, n = snapshot_dir(tmp_path)
    assert n == 1 and {e[0] for e in snap} == {"a.dcm", ".a.dcm.part"}
    assert snapshot_dir(tmp_path / "missing") == (frozenset(), 0)


@pytest.mark.parametrize("polling_only", [False, True])
def test_thread_picks_up_a_series(tmp_path: Path, polling_only: bool) -> None:
    watch = tmp_path / "watch"
    sink = Sink()
    w = SeriesWatcher(
        watch, on_series=sink, quiet_period_s=0.2, poll_interval_s=0.1, use_polling_only=polling_only
    )
    w.start()
    try:
        assert w.state()["running"] and w.state()["mode"] == ("polling" if polling_only else "events+polling")
        series(tmp_path / "staging", series_uid="1.2.3.80").__len__()
        (tmp_path / "staging").rename(watch / "s")
        assert sink.event.wait(20.0), "no series delivered"
        assert sink.arrivals[0].series_uid == "1.2.3.80" and np.asarray(sink.arrivals[0].volume.voxels).size
    finally:
        w.stop()
    assert not w.state()["running"]


def test_watchdogs_stop_race_is_debug_and_other_watchdog_errors_stay_errors(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The watcher installs the filter when it starts OS events; then watchdog's own shutdown-race
    line (logged at ERROR by the same code path it takes after Observer.stop()) is not an ERROR,
    while any other ERROR of that logger still is."""
    import logging

    from service.intake.watcher import WATCHDOG_STOP_RACE

    w, _, _ = make(tmp_path)
    w.start()
    try:
        assert w.mode == "events+polling"
    finally:
        w.stop()
    inotify_log = logging.getLogger("watchdog.observers.inotify")
    with caplog.at_level(logging.INFO):
        inotify_log.error(WATCHDOG_STOP_RACE)
        inotify_log.error("inotify watch limit reached")
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert errors == ["inotify watch limit reached"]
    with caplog.at_level(logging.DEBUG):
        caplog.clear()
        inotify_log.error(WATCHDOG_STOP_RACE)
    assert [(r.levelname, r.getMessage()) for r in caplog.records] == [("DEBUG", WATCHDOG_STOP_RACE)]
