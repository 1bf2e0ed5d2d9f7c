"""Is a recorded scan usable for registration?  The refusals before any pixel is read."""

from __future__ import annotations

from drivers.errors import RobotLinkError
from registration.errors import DicomSeriesError, RobotMovedError
from service.records import JointSnapshot, ScanRecord


def check_capture(scan: ScanRecord, window_s: float) -> tuple[JointSnapshot, tuple[float, ...]]:
    """The scan's joint snapshot and joints, or the refusal.

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
        The robot moved during the scan, or its stillness could not be established.
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
    if snap.joints_rad is None:
        if snap.link_state == "down":
            raise RobotLinkError(
                f"robot link {snap.link_url} was down when {what} arrived ({snap.link_reason}); "
                "no joint angles, so no robot-space sphere positions; "
                "restore the link (GET /status) and rescan"
            )
        raise RobotMovedError(f"{what}: joint angles during the scan are unknown: {snap.stillness_reason}")
    if not snap.still:
        if snap.link_state == "down":
            raise RobotLinkError(
                f"robot link {snap.link_url} went down around {what}: {snap.stillness_reason}; "
                "restore the link (GET /status) and rescan"
            )
        raise RobotMovedError(
            f"the robot moved during {what}, or its stillness could not be established: "
            f"{snap.stillness_reason}; keep the robot still for {window_s:g} s before and during the scan, "
            "then rescan"
        )
    return snap, snap.joints_rad
