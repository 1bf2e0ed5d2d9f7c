"""Is a recorded scan usable for registration?  The refusals before any pixel is read."""

from __future__ import annotations

from drivers.errors import RobotLinkError
from registration.errors import DicomSeriesError, JointHistoryIncompleteError, RobotMovedError
from service.records import JointSnapshot, ScanRecord


def check_capture(scan: ScanRecord, window_s: float) -> tuple[JointSnapshot, tuple[float, ...]]:
    """The scan's joint snapshot and joints, or the refusal, decided by the typed
    :attr:`JointSnapshot.verdict` alone (the reason text is quoted, never parsed).

    Parameters
    ----------
    scan : ScanRecord
    window_s : float
        The stillness window (s), quoted in the refusal.

    Raises
    ------
    DicomSeriesError
        The scan is ``invalid``.
    RobotLinkError
        No joints were captured (link not running or down).
    RobotMovedError
        A joint deviated over the limit during the scan (verdict ``moved``).
    JointHistoryIncompleteError
        The joint history does not cover the scan (verdict ``incomplete``): not watched, frames
        missing, a reconnect; the robot's stillness is unknown.
    """
    if scan.status != "complete":
        raise DicomSeriesError(
            f"scan {scan.id} (series {scan.series_uid}, {scan.folder}) is unusable: {scan.reason}"
        )
    snap = scan.snapshot
    what = f"scan {scan.id} (series {scan.series_uid})"
    if snap is None:
        raise RobotLinkError(
            f"no joint angles were captured for {what}; the robot link was not running; rescan with the link "
            "connected"
        )
    rescan = f"keep the robot still for {window_s:g} s before and during the scan, then rescan"
    if snap.verdict == "moved":
        raise RobotMovedError(f"the robot moved during {what}: {snap.stillness_reason}; {rescan}")
    if snap.verdict != "still" or snap.joints_rad is None:  # incomplete (never the reason text)
        if snap.link_state == "down":
            raise RobotLinkError(
                f"robot link {snap.link_url} was down around {what} ({snap.link_reason}): "
                f"{snap.stillness_reason}; no joint angles cover the scan; restore the link (GET /status) "
                "and rescan"
            )
        raise JointHistoryIncompleteError(
            f"the joint history of {what} does not cover the scan, so whether the robot was still is unknown "
            f"(not that it moved): {snap.stillness_reason}; check the robot link (GET /status: connected, "
            f"history_s >= {window_s:g}) and {rescan}"
        )
    assert snap.joints_rad is not None
    return snap, snap.joints_rad
