"""A folder recorded ``invalid`` that did not change is not reported as changed at the next start-up
(issue 42, item 6): its bytes are hashed and compared first; a folder whose bytes did change still is."""

from __future__ import annotations

from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path

import pytest

from service.events import Event
from service.intake.recording import Intake, SeriesArrival
from service.intake.scan_lifecycle import ScanLifecycle, hash_files
from service.intake.volume_cache import VolumeCache
from service.intake.watcher import folder_uid
from service.records import JointSnapshot
from service.store import Database

REASON = "no readable CT series: 2 file(s) skipped"


class NoLink:
    """The intake's :class:`~service.intake.recording.SnapshotSource` with no robot link."""

    def snapshot(
        self, first_seen_t_s: float, last_change_t_s: float, *, preexisting: bool = False
    ) -> JointSnapshot:
        return JointSnapshot(link_url="", link_state="disconnected", window_s=1.0, verdict="incomplete")


@pytest.fixture
def intake(tmp_path: Path) -> Iterator[tuple[Intake, list[Event], list[tuple[int, str]]]]:
    db = Database.open(tmp_path / "data" / "x.sqlite3")
    events: list[Event] = []
    withdrawn: list[tuple[int, str]] = []
    lifecycle = ScanLifecycle(db, VolumeCache(), events.append, lambda i, why: withdrawn.append((i, why)))
    yield Intake(db, NoLink(), VolumeCache(), events.append, lifecycle), events, withdrawn
    db.close()


def _junk_arrival(folder: Path) -> SeriesArrival:
    return SeriesArrival(
        series_uid=folder_uid(folder), folder=folder, first_seen_t_s=0.0, last_change_t_s=0.0,
        first_seen_at=datetime.now(UTC), n_files=2, error=REASON, preexisting=True,
        files=hash_files(sorted(folder.iterdir())),
    )  # fmt: skip


def test_an_unchanged_invalid_folder_is_not_reported_changed(
    tmp_path: Path, intake: tuple[Intake, list[Event], list[tuple[int, str]]]
) -> None:
    rec, events, withdrawn = intake
    junk = tmp_path / "watch" / "junk"
    junk.mkdir(parents=True)
    (junk / "notes.txt").write_text("not DICOM")
    (junk / "image.dcm").write_bytes(b"\0" * 300)
    rec(_junk_arrival(junk))  # first seen
    n_first = len(events)
    rec(_junk_arrival(junk))  # the next start-up's first pass: same bytes, same verdict
    assert events[n_first:] == [] and withdrawn == []
    scan = rec.db.scans.by_series_uid(folder_uid(junk))
    assert scan is not None and scan.status == "invalid" and scan.reason == REASON
    # its bytes change: that is a change, and said
    (junk / "image.dcm").write_bytes(b"\1" * 300)
    rec(_junk_arrival(junk))
    kinds = [type(e).__name__ for e in events[n_first:]]
    assert "ScanReplaced" in kinds, kinds
    assert any("image.dcm" in why for _, why in withdrawn)


def test_the_watcher_hashes_only_the_regular_files_of_a_junk_folder(tmp_path: Path) -> None:
    import os

    from service.intake.watcher import folder_hashes

    (tmp_path / "a.dcm").write_bytes(b"x" * 10)
    (tmp_path / ".a.dcm.part").write_bytes(b"partial")
    (tmp_path / "link").symlink_to(tmp_path / "a.dcm")
    os.mkfifo(tmp_path / "fifo")  # never opened: opening a FIFO would block
    assert folder_hashes(tmp_path) == hash_files([tmp_path / "a.dcm"])
