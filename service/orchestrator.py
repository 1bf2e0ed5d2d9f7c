"""The registration pipeline behind ``POST /register`` and ``POST /verify``.

load → MAR → detect (``registration.detection``) → robot-space sphere centres
(``registration.kinematics.sphere_centres_robot_mm`` with the joints captured at the
scan's arrival) → register (``registration.register.register_points``) → gates →
store → make current.

Each call runs on a worker thread (the API awaits it with ``anyio.to_thread``) under one
lock, so concurrent calls run one after the other and never interleave their writes.
Every outcome is stored: a refusal (robot moved, robot link down, too few spheres,
ambiguous, FRE over the gate, bad scan) becomes a ``refused`` registration with the
reason, the exception is re-raised (the API answers problem details) and the previous
current registration stays current.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from drivers.errors import RobotLinkError
from registration import __version__
from registration.errors import (
    DicomSeriesError,
    OarmRegError,
    RegistrationError,
    RobotMovedError,
)
from service.db import Database, ScanRow, utc_now
from service.settings import Settings

log = logging.getLogger(__name__)

VOLUME_CACHE_SIZE = 2
"""Loaded volumes kept in memory (a 512 × 512 × 192 int16 scan is 100 MB)."""


class NotFoundError(OarmRegError):
    http_status = 404
    title = "Not found"


class NoScanError(OarmRegError):
    http_status = 409
    title = "No complete scan"


class NoCurrentRegistrationError(RegistrationError):
    title = "No current registration"


class VerificationRefusedError(RegistrationError):
    title = "Verification refused"


class InternalError(OarmRegError):
    http_status = 500
    title = "Internal error"


def default_targets_robot_mm(
    phantom_centre_robot_mm: NDArray[np.float64], distance_mm: float
) -> NDArray[np.float64]:
    """The 6 points ``distance_mm`` from the phantom centre along ±x, ±y, ±z of the robot frame, (6, 3) mm."""
    offsets = np.vstack([np.eye(3), -np.eye(3)]) * distance_mm
    return np.asarray(phantom_centre_robot_mm.reshape(1, 3) + offsets, dtype=np.float64)


class Orchestrator:
    """Runs registrations and verifications; holds the current registration in memory.

    Parameters
    ----------
    settings, db
    phantom : registration.phantom.Phantom
    robot_model : registration.kinematics.RobotModel
    publish : callable
        ``publish(event, data)``, thread-safe.
    """

    def __init__(
        self,
        settings: Settings,
        db: Database,
        phantom: Any,
        robot_model: Any,
        publish: Callable[[str, dict[str, Any]], None],
    ) -> None:
        self.settings = settings
        self.db = db
        self.phantom = phantom
        self.robot_model = robot_model
        self.publish = publish
        self.config_hash = settings.config_hash()
        self.tool0_from_phantom = settings.robot.tool0_from_phantom.matrix()
        self._lock = threading.Lock()
        self._volumes: OrderedDict[str, Any] = OrderedDict()
        self._volumes_lock = threading.Lock()
        self._current: dict[str, Any] | None = db.current_registration()
        self.busy = False
        if self._current is not None:
            log.info(
                "restored current registration %d (scan %s, FRE %.3f mm)",
                self._current["id"],
                self._current["series_uid"],
                self._current["fre_mm"] or float("nan"),
            )

    # ---- state ----------------------------------------------------------------------------

    @property
    def current(self) -> dict[str, Any] | None:
        """The current (accepted) registration record, or None (atomic reference read)."""
        return self._current

    def cache_volume(self, series_uid: str, volume: Any) -> None:
        with self._volumes_lock:
            self._volumes[series_uid] = volume
            self._volumes.move_to_end(series_uid)
            while len(self._volumes) > VOLUME_CACHE_SIZE:
                self._volumes.popitem(last=False)

    def _volume(self, scan: ScanRow) -> Any:
        with self._volumes_lock:
            vol = self._volumes.get(scan.series_uid)
        if vol is not None:
            return vol
        from registration.dicom import load_series

        try:
            vol = load_series(scan.folder, series_uid=scan.series_uid)
        except OSError as e:
            raise DicomSeriesError(
                f"series {scan.series_uid} can no longer be read from {scan.folder}: {e}; re-export the scan"
            ) from None
        self.cache_volume(scan.series_uid, vol)
        return vol

    # ---- shared steps ---------------------------------------------------------------------

    def _resolve_scan(self, scan_id: int | None) -> ScanRow:
        if scan_id is None:
            scan = self.db.latest_complete_scan()
            if scan is None:
                raise NoScanError(
                    f"no complete scan has arrived in {self.settings.watch_dir} yet; export the O-arm scan "
                    "there (GET /scans lists what the watcher has seen)"
                )
            return scan
        scan = self.db.get_scan(scan_id)
        if scan is None:
            raise NotFoundError(f"scan {scan_id} does not exist; GET /scans lists the recorded scans")
        return scan

    def _check_scan(self, scan: ScanRow) -> dict[str, Any]:
        """Raise the refusal for an unusable scan / joint snapshot; return the snapshot."""
        if scan.status != "complete":
            raise DicomSeriesError(
                f"scan {scan.id} (series {scan.series_uid}, {scan.folder}) is unusable: {scan.reason}"
            )
        snap = scan.snapshot
        if snap is None:
            raise RobotLinkError(
                f"no joint angles were captured for scan {scan.id} (series {scan.series_uid}); "
                "the robot link was not running; rescan with the link connected"
            )
        if snap.get("joints_rad") is None:
            if snap.get("link_state") == "down":
                raise RobotLinkError(
                    f"robot link {snap['link_url']} was down when scan {scan.id} (series {scan.series_uid}) "
                    f"arrived ({snap.get('link_reason', '')}); no joint angles, so no robot-space sphere "
                    "positions; restore the link (GET /status) and rescan"
                )
            raise RobotMovedError(
                f"scan {scan.id} (series {scan.series_uid}): joint angles during the scan are unknown: "
                f"{snap.get('stillness_reason', '')}"
            )
        if not snap.get("still"):
            if snap.get("link_state") == "down":
                raise RobotLinkError(
                    f"robot link {snap['link_url']} went down around scan {scan.id} (series "
                    f"{scan.series_uid}): "
                    f"{snap.get('stillness_reason', '')}; restore the link (GET /status) and rescan"
                )
            raise RobotMovedError(
                f"the robot moved during scan {scan.id} (series {scan.series_uid}), or its "
                f"stillness could not "
                f"be established: {snap.get('stillness_reason', '')}; keep the robot still for "
                f"{self.settings.stillness.window_s:g} s before and during the scan, then rescan"
            )
        return snap

    def _detect(self, volume: Any) -> Any:
        from registration.detection import DetectionParams, detect_spheres

        ds = self.settings.detection
        kw: dict[str, Any] = {
            "use_mar": ds.use_mar,
            "sphere_diameter_mm": float(self.phantom.sphere_diameter_mm),
        }
        if ds.method != "default":
            kw["method"] = ds.method
        return detect_spheres(volume, DetectionParams(**kw))

    def _robot_points(self, joints_rad: list[float]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Sphere centres (N, 3) and phantom centre (3,) in the robot frame, mm."""
        from registration.kinematics import sphere_centres_robot_mm

        centres = sphere_centres_robot_mm(
            self.robot_model, joints_rad, self.tool0_from_phantom, self.phantom.centres_phantom_mm
        )
        robot_from_phantom = self.robot_model.robot_from_tool0(joints_rad) @ self.tool0_from_phantom
        return np.asarray(centres, dtype=np.float64), np.asarray(robot_from_phantom[:3, 3], dtype=np.float64)

    def _reg_params(self) -> Any:
        from registration.register import RegistrationParams

        q = self.settings.quality
        return RegistrationParams(
            min_matched=q.min_matched_spheres,
            min_runner_up_margin=q.min_symmetry_margin,
            max_fre_mm=q.max_fre_mm,
        )

    def _sphere_id(self, robot_index: int) -> str:
        ids = self.phantom.filled_ids
        return str(ids[robot_index]) if 0 <= robot_index < len(ids) else str(robot_index)

    # ---- register -------------------------------------------------------------------------

    def register(
        self, scan_id: int | None = None, targets_image_mm: list[list[float]] | None = None
    ) -> dict[str, Any]:
        """Run the pipeline; return the stored accepted record, or raise the refusal (stored too).

        Raises
        ------
        NotFoundError, NoScanError
            Nothing to register (not stored).
        OarmRegError, RobotLinkError
            Refusal; stored as ``refused``; ``e.registration_id`` is the stored record's id.
        """
        with self._lock:
            self.busy = True
            try:
                return self._register_locked(scan_id, targets_image_mm)
            finally:
                self.busy = False

    def _register_locked(
        self, scan_id: int | None, targets_image_mm: list[list[float]] | None
    ) -> dict[str, Any]:
        scan = self._resolve_scan(scan_id)
        t0 = time.perf_counter()
        record: dict[str, Any] = {
            "created_at": utc_now(),
            "scan_id": scan.id,
            "series_uid": scan.series_uid,
            "config_hash": self.config_hash,
            "software_version": __version__,
            "targets_image_mm": targets_image_mm,
        }
        if scan.snapshot is not None:
            record["joints_rad"] = scan.snapshot.get("joints_rad")
            record["joints_received_at"] = scan.snapshot.get("joints_received_at")
        try:
            figures, matrix = self._compute_registration(scan, targets_image_mm)
        except (OarmRegError, RobotLinkError) as e:
            self._store_refusal(record, e, t0)
            raise
        except Exception as e:  # a bug: store it as refused, answer 500
            log.exception("registration of scan %d failed unexpectedly", scan.id)
            err = InternalError(
                f"registration of scan {scan.id} failed unexpectedly: {type(e).__name__}: {e}"
            )
            self._store_refusal(record, err, t0)
            raise err from e
        record.update(
            status="accepted",
            image_from_robot=matrix.tolist(),
            fre_mm=figures["fre_mm"],
            figures=figures,
            duration_s=time.perf_counter() - t0,
        )
        reg_id = self.db.insert_registration(record, make_current=True)
        stored = self.db.get_registration(reg_id)
        assert stored is not None
        self._current = stored
        log.info(
            "registration %d accepted: scan %d (series %s), FRE %.3f mm, %d/%d spheres matched, %.2f s",
            reg_id,
            scan.id,
            scan.series_uid,
            figures["fre_mm"],
            figures["n_matched"],
            figures["n_expected"],
            record["duration_s"],
        )
        self.publish(
            "registration_done",
            {
                "registration_id": reg_id,
                "scan_id": scan.id,
                "series_uid": scan.series_uid,
                "fre_mm": figures["fre_mm"],
                "n_matched": figures["n_matched"],
            },
        )
        return stored

    def _store_refusal(self, record: dict[str, Any], e: Exception, t0: float) -> None:
        title = str(getattr(e, "title", "Registration refused"))
        status = int(getattr(e, "http_status", 409))
        record.update(
            status="refused",
            reason=str(e),
            problem_title=title,
            http_status=status,
            duration_s=time.perf_counter() - t0,
        )
        try:
            reg_id = self.db.insert_registration(record, make_current=False)
        except Exception:
            log.exception("could not store the refused registration of scan %s", record.get("scan_id"))
            return
        e.registration_id = reg_id  # type: ignore[attr-defined]
        log.warning("registration %d refused (%s): %s", reg_id, title, e)
        self.publish(
            "registration_refused",
            {
                "registration_id": reg_id,
                "scan_id": record.get("scan_id"),
                "series_uid": record.get("series_uid"),
                "title": title,
                "reason": str(e),
            },
        )

    def _compute_registration(
        self, scan: ScanRow, targets_image_mm: list[list[float]] | None
    ) -> tuple[dict[str, Any], NDArray[np.float64]]:
        from registration.frames import apply, invert
        from registration.quality import predicted_tre_mm
        from registration.register import register_points

        timings: dict[str, float] = {}
        snap = self._check_scan(scan)
        t = time.perf_counter()
        volume = self._volume(scan)
        timings["load_s"] = time.perf_counter() - t
        t = time.perf_counter()
        det = self._detect(volume)
        timings["detect_s"] = time.perf_counter() - t
        robot_mm, centre_robot_mm = self._robot_points(snap["joints_rad"])
        image_mm = np.asarray(det.centres_image_mm, dtype=np.float64).reshape(-1, 3)
        default_targets = default_targets_robot_mm(
            centre_robot_mm, self.settings.quality.default_target_distance_mm
        )
        params = self._reg_params()
        t = time.perf_counter()
        res = register_points(
            robot_mm, image_mm, params=params, targets_robot_mm=default_targets, phantom=self.phantom
        )
        targets_img: NDArray[np.float64]
        predicted_tre = np.asarray(res.predicted_tre_mm, dtype=np.float64)
        if targets_image_mm:
            # the UI's targets are in the image frame; Fitzpatrick's TRE needs them in the frame of the
            # fiducials, so map them back through the registration just computed
            targets_img = np.asarray(targets_image_mm, dtype=np.float64).reshape(-1, 3)
            targets_robot = apply(invert(res.image_from_robot), targets_img)
            predicted_tre = predicted_tre_mm(res.fle_mm, robot_mm[res.robot_indices], targets_robot)
        else:
            targets_img = apply(res.image_from_robot, default_targets)
        timings["register_s"] = time.perf_counter() - t
        robot_idx = [int(i) for i in np.asarray(res.robot_indices)]
        image_idx = [int(i) for i in np.asarray(res.image_indices)]
        residuals = [float(v) for v in np.asarray(res.residuals_mm)]
        figures: dict[str, Any] = {
            "fre_mm": float(res.fre_mm),
            "fle_mm": float(res.fle_mm),
            "n_expected": int(res.n_expected),
            "n_detected": int(res.n_detected),
            "n_matched": int(res.n_matched),
            "symmetry_margin": int(res.symmetry_margin),
            "rotation_det": float(res.rotation_det),
            "predicted_tre_mm": [float(v) for v in predicted_tre],
            "targets_image_mm": targets_img.tolist(),
            "targets_source": "request"
            if targets_image_mm
            else (
                f"default: {self.settings.quality.default_target_distance_mm:g} mm from the phantom centre "
                "along ±x, ±y, ±z of the robot frame"
            ),
            "spheres": [
                {"sphere": self._sphere_id(ri), "robot_index": ri, "image_index": ii, "residual_mm": r}
                for ri, ii, r in zip(robot_idx, image_idx, residuals, strict=False)
            ],
            "detection": {
                "method": str(getattr(det, "method", "")),
                "n_rejected": len(getattr(det, "rejections", ())),
                "timings_s": dict(getattr(det, "timings_s", {}) or {}),
            },
            "provenance": {
                "series_uid": scan.series_uid,
                "frame_of_reference_uid": scan.frame_of_reference_uid,
                "scan_folder": scan.folder,
                "joints_rad": snap["joints_rad"],
                "joints_received_at": snap.get("joints_received_at"),
                "robot_link": snap.get("link_url"),
                "robot_model": self.settings.robot.model,
                "tool0_from_phantom": self.tool0_from_phantom.tolist(),
                "phantom": str(self.phantom.name),
                "config_hash": self.config_hash,
                "software_version": __version__,
            },
            "timings_s": {**timings, **{f"register.{k}": float(v) for k, v in dict(res.timings_s).items()}},
        }
        return figures, np.asarray(res.image_from_robot, dtype=np.float64)

    # ---- verify ---------------------------------------------------------------------------

    def verify(self, scan_id: int | None = None) -> dict[str, Any]:
        """The paper's error analysis (Bai 2018 §3, eq. 10) of a newer scan against the current registration.

        Raises
        ------
        NoCurrentRegistrationError, VerificationRefusedError, OarmRegError, RobotLinkError
        """
        with self._lock:
            self.busy = True
            try:
                return self._verify_locked(scan_id)
            finally:
                self.busy = False

    def _verify_locked(self, scan_id: int | None) -> dict[str, Any]:
        from registration.verification import verify_registration

        current = self._current
        if current is None:
            raise NoCurrentRegistrationError(
                "there is no current registration to verify; POST /register first"
            )
        scan = self._resolve_scan(scan_id)
        if scan.id == current["scan_id"] or (current["scan_id"] is not None and scan.id < current["scan_id"]):
            raise VerificationRefusedError(
                f"scan {scan.id} is not newer than scan {current['scan_id']} of the current registration "
                f"{current['id']}; move the robot, scan again and verify against that scan"
            )
        snap = self._check_scan(scan)
        volume = self._volume(scan)
        det = self._detect(volume)
        robot_mm, _ = self._robot_points(snap["joints_rad"])
        image_mm = np.asarray(det.centres_image_mm, dtype=np.float64).reshape(-1, 3)
        matrix = np.asarray(current["image_from_robot"], dtype=np.float64)
        res = verify_registration(matrix, robot_mm, image_mm, params=self._reg_params())
        errors = [float(v) for v in np.asarray(res.errors_mm)]
        robot_idx = [int(i) for i in np.asarray(res.robot_indices)]
        gate = self.settings.quality.max_verification_error_mm
        figures = {
            "errors": [
                {"sphere": self._sphere_id(ri), "robot_index": ri, "error_mm": e}
                for ri, e in zip(robot_idx, errors, strict=False)
            ],
            "n_expected": len(robot_mm),
            "n_detected": len(image_mm),
            "n_matched": len(errors),
            "max_verification_error_mm": gate,
            "joints_rad": snap["joints_rad"],
            "joints_received_at": snap.get("joints_received_at"),
        }
        record = {
            "registration_id": current["id"],
            "scan_id": scan.id,
            "series_uid": scan.series_uid,
            "passed": float(res.max_mm) <= gate,
            "mean_mm": float(res.mean_mm),
            "rms_mm": float(res.rms_mm),
            "max_mm": float(res.max_mm),
            "figures": figures,
            "config_hash": self.config_hash,
            "software_version": __version__,
        }
        ver_id = self.db.insert_verification(record)
        png = self.settings.data_dir / "histograms" / f"verification-{ver_id}.png"
        try:
            title = f"Verification {ver_id}: scan {scan.id} vs registration {current['id']}"
            write_histogram(np.asarray(errors), png, title=title)
            self.db.set_verification_histogram(ver_id, str(png))
        except Exception:
            log.exception("verification %d: writing the histogram %s failed", ver_id, png)
        stored = self.db.get_verification(ver_id)
        assert stored is not None
        self.publish(
            "verification_done",
            {
                "verification_id": ver_id,
                "registration_id": current["id"],
                "scan_id": scan.id,
                "mean_mm": record["mean_mm"],
                "max_mm": record["max_mm"],
                "passed": record["passed"],
            },
        )
        return stored


def write_histogram(errors_mm: NDArray[np.float64], path: Path, *, title: str) -> None:
    """Histogram of per-sphere position errors as a PNG (Bai 2018 fig. 7), via :mod:`service.histogram`."""
    from service.histogram import write_error_histogram

    path.parent.mkdir(parents=True, exist_ok=True)
    write_error_histogram(errors_mm, path, title=title)
