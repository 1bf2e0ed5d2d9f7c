"""Calibration sessions in the service: ``POST /calibrations`` → a worker thread.

:meth:`CalibrationJobs.start` resolves the scans (given ids, or the last K complete ones), refuses
at once — stored with the reason — fewer than ``MIN_POSES`` scans or scans from several O-arm
placements (FrameOfReferenceUID (0020,0052)), stores a ``running`` row and starts one worker
thread.  The worker checks each scan's recorded capture (robot still, joints known), detects the
spheres, matches them with the nominal model and rod (:func:`registration.calibration.solver.match_pose`),
and runs :func:`registration.calibration.solver.calibrate`; it publishes ``calibration_progress`` (pose i
of K, then the fit), then ``calibration_done`` or ``calibration_refused`` (stored with the reason).
The calibrated URDF is written to ``data_dir/calibrations/<id>/robot.urdf`` and kept in the row.

:meth:`CalibrationJobs.activate` makes a finished calibration the one ``/register`` uses (its
model and rod), retires every accepted registration (none is current until the next
``/register``) and publishes ``calibration_activated`` and ``registration_retired``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from drivers.errors import RobotLinkError
from registration import __version__
from registration.calibration.records import (
    MIN_POSES,
    CalibrationParams,
    MatchedPose,
)
from registration.calibration.solver import (
    calibrate,
    check_session,
    match_pose,
)
from registration.calibration.urdf import read_chain, write_calibrated_urdf
from registration.errors import OarmRegError
from registration.model.kinematics import RobotModel, sphere_centres_robot_mm
from registration.model.phantom import Phantom
from service.error_map import http_status_of, title_of
from service.errors import (
    CalibrationBusyError,
    CalibrationNotUsableError,
    CalibrationRefusedError,
    CalibrationStoppedError,
    InternalError,
    NotFoundError,
)
from service.events import (
    CalibrationActivated,
    CalibrationDone,
    CalibrationProgress,
    CalibrationRefused,
    CalibrationStarted,
    Publish,
    RegistrationRetired,
)
from service.intake.volume_cache import VolumeCache
from service.records import ScanRecord
from service.registrations.orchestrator import Orchestrator
from service.registrations.robot_side import FINGERPRINT_KEY, changed_settings
from service.registrations.scan_checks import check_capture
from service.settings import Settings
from service.store import Database
from service.store.base import utc_now
from service.store.calibrations import Activation, CalibrationRecord

log = logging.getLogger(__name__)

URDF_FILE = "robot.urdf"


@dataclass(frozen=True)
class CalibrationRequest:
    """What ``POST /calibrations`` asks for: ``scan_ids`` or the ``last`` K complete scans."""

    scan_ids: tuple[int, ...] | None = None
    last: int | None = None
    parameter_set: Literal["full", "offsets", "hand-eye"] = "full"
    drop_weak: bool = False
    max_condition: float | None = None
    """Optional extra refusal on the identification condition number (``--max-condition``)."""

    def params(self, target_rms_mm: float | None = None) -> CalibrationParams:
        """``target_rms_mm``: the planner's target the result is compared with
        (``calibration.target_rms_mm``)."""
        p: CalibrationParams = calibration_params(
            parameter_set=self.parameter_set,
            drop_weak=self.drop_weak,
            max_condition=self.max_condition,
            target_rms_mm=target_rms_mm,
        )
        return p


def calibration_hash(urdf_text: str, tool0_from_phantom: Sequence[Sequence[float]]) -> str:
    """SHA-256 of the calibrated URDF and the rod: what a registration's provenance names."""
    h = hashlib.sha256(urdf_text.encode())
    h.update(json.dumps([[float(v) for v in row] for row in tool0_from_phantom]).encode())
    return h.hexdigest()


class CalibrationJobs:
    """One calibration at a time on a worker thread; activation through the orchestrator."""

    def __init__(
        self,
        settings: Settings,
        db: Database,
        orchestrator: Orchestrator,
        phantom: Phantom,
        nominal_model: RobotModel,
        volumes: VolumeCache,
        publish: Publish,
    ) -> None:
        self.settings, self.db, self.orchestrator = settings, db, orchestrator
        self.phantom, self.nominal_model, self.volumes, self.publish = (
            phantom,
            nominal_model,
            volumes,
            publish,
        )
        self.nominal_rod = settings.robot.tool0_from_phantom.matrix()
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.inactive_reason = ""
        """Why the active calibration is not used (made under other robot settings; ``/status``)."""

    # ---- life ----------------------------------------------------------------------------

    def restore(self) -> None:
        """At start-up: refuse calibrations a previous run left ``running``; use the active one."""
        ids = self.db.calibrations.refuse_interrupted("the service stopped while this calibration ran; retry")
        if ids:
            log.warning("calibration(s) %s were interrupted by a restart: marked refused", ids)
        act = self.db.calibrations.active()
        changed = (
            []
            if act is None
            else changed_settings(act.params.get(FINGERPRINT_KEY), self.orchestrator.robot_settings)
        )
        if act is not None and changed:
            self.inactive_reason = (
                f"calibration {act.id} was made under other robot settings ({', '.join(changed)} changed): "
                "it is not used; restore those settings, or calibrate again under these"
            )
            log.warning("%s", self.inactive_reason)
        elif act is not None:
            model, rod = self._model_of(act)
            self.orchestrator.use_calibration(model, rod, self._ref(act))
            log.info("active calibration %d (%s) restored", act.id, act.calibration_hash[:12])

    def stop(self) -> None:
        """Ask a running worker to stop after its current step and wait for it."""
        self._stop.set()
        t = self._thread
        if t is not None:
            t.join()

    @property
    def running(self) -> bool:
        t = self._thread
        return t is not None and t.is_alive()

    # ---- start ---------------------------------------------------------------------------

    def _resolve(self, req: CalibrationRequest) -> list[ScanRecord]:
        if req.scan_ids is not None:
            scans = []
            for sid in req.scan_ids:
                s = self.db.scans.get(sid)
                if s is None:
                    raise NotFoundError(f"scan {sid} does not exist; GET /scans lists the recorded scans")
                scans.append(s)
            return scans
        n = int(req.last or 0)
        complete = [s for s in self.db.scans.list(limit=max(n, 1) * 4 + 50) if s.status == "complete"]
        return list(reversed(complete[:n]))

    def start(self, req: CalibrationRequest) -> CalibrationRecord | CalibrationRefusal:
        """Check the request, store a ``running`` row and start the worker; returns the row, or the
        refusal of a request refused at once (stored as ``refused``: :class:`CalibrationRefusal`).

        Raises
        ------
        NotFoundError
            An unknown scan id (not stored).
        CalibrationBusyError
            Another calibration is running (not stored).
        """
        with self._lock:
            if self.running:
                raise CalibrationBusyError("a calibration is already running; wait for calibration_done")
            scans = self._resolve(req)
            try:
                self._check(scans)
            except OarmRegError as e:
                return self._store_refusal(req, scans, e)
            draft = self._draft(req, scans, "running")
            cal_id = self.db.calibrations.insert(draft)
            self._stop.clear()
            self._thread = threading.Thread(
                target=self._work,
                args=(cal_id, scans, req.params(self.settings.calibration.target_rms_mm)),
                name=f"calibration-{cal_id}",
            )
            # announced before the worker can publish its first progress: a listener sees started first
            self.publish(CalibrationStarted(calibration_id=cal_id, scan_ids=draft.scan_ids))
            self._thread.start()
        stored = self.db.calibrations.get(cal_id)
        assert stored is not None
        return stored

    @staticmethod
    def _check(scans: list[ScanRecord]) -> None:
        """Refuse (:class:`CalibrationRefusedError`, or the session check's error) a scan named twice,
        an incomplete scan or scans from different placements."""
        if len({s.id for s in scans}) != len(scans):
            raise CalibrationRefusedError("each scan may appear once in a calibration")
        bad = [f"scan {s.id} ({s.status}: {s.reason})" for s in scans if s.status != "complete"]
        if bad:
            raise CalibrationRefusedError(f"calibration scans must be complete; {', '.join(bad)}")
        stubs = [
            MatchedPose(
                name=f"scan {s.id}",
                joints_rad=np.zeros(0),
                sphere_indices=np.zeros(0, dtype=np.int64),
                centres_image_mm=np.zeros((0, 3)),
                series_uid=s.series_uid,
                frame_of_reference_uid=s.frame_of_reference_uid,
            )
            for s in scans
        ]
        check_session(stubs, MIN_POSES)

    def _draft(self, req: CalibrationRequest, scans: list[ScanRecord], status: Any) -> CalibrationRecord:
        fors = sorted({s.frame_of_reference_uid for s in scans})
        return CalibrationRecord(
            created_at=utc_now(),
            status=status,
            scan_ids=tuple(s.id for s in scans),
            params={
                **dataclasses.asdict(req.params(self.settings.calibration.target_rms_mm)),
                "request": _request_json(req),
                FINGERPRINT_KEY: self.orchestrator.robot_settings,
            },
            config_hash=self.orchestrator.config_hash,
            software_version=__version__,
            frame_of_reference_uid=fors[0] if len(fors) == 1 else "",
        )

    def _store_refusal(
        self, req: CalibrationRequest, scans: list[ScanRecord], err: OarmRegError
    ) -> CalibrationRefusal:
        rec = dataclasses.replace(
            self._draft(req, scans, "refused"),
            reason=str(err),
            problem_title=title_of(err),
            finished_at=utc_now(),
            duration_s=0.0,
        )
        cal_id = self.db.calibrations.insert(rec)
        log.warning("calibration %d refused (%s): %s", cal_id, rec.problem_title, err)
        self.publish(
            CalibrationRefused(
                calibration_id=cal_id, title=rec.problem_title, reason=str(err), status=http_status_of(err)
            )
        )
        return CalibrationRefusal(cal_id, err)

    # ---- the worker ----------------------------------------------------------------------

    def _work(self, cal_id: int, scans: list[ScanRecord], params: CalibrationParams) -> None:
        t0 = time.perf_counter()
        try:
            matched, geometry = self._match_all(cal_id, scans)
            self._progress(cal_id, "fit", len(scans), len(scans))
            chain = read_chain(self.nominal_model.urdf_path)
            result = calibrate(
                matched,
                chain,
                self.nominal_rod,
                self.phantom.centres_phantom_mm,
                params,
                scan_volume=None if geometry is None else geometry.scan_volume(),
            )
            self._finish_done(cal_id, scans, matched, result, params, time.perf_counter() - t0)
        except (OarmRegError, RobotLinkError) as e:
            self._finish_refused(cal_id, e, time.perf_counter() - t0)
        except Exception as e:  # a bug: stored as refused, logged with its traceback
            log.exception("calibration %d failed unexpectedly", cal_id)
            err = InternalError(f"calibration {cal_id} failed unexpectedly: {type(e).__name__}: {e}")
            self._finish_refused(cal_id, err, time.perf_counter() - t0)

    def _progress(
        self,
        cal_id: int,
        stage: str,
        i: int,
        k: int,
        *,
        scan_id: int | None = None,
        n_matched: int | None = None,
    ) -> None:
        self.publish(
            CalibrationProgress(
                calibration_id=cal_id, stage=stage, pose=i, n_poses=k, scan_id=scan_id, n_matched=n_matched
            )
        )

    def _match_all(self, cal_id: int, scans: list[ScanRecord]) -> tuple[list[MatchedPose], Any]:
        """Matched poses and the first scan's series geometry (the session's scan volume)."""
        from registration.imaging.scan_geometry import series_geometry

        det_params = self.orchestrator.params.detection
        out = []
        geometry = None
        for i, scan in enumerate(scans, start=1):
            if self._stop.is_set():
                raise CalibrationStoppedError("the service is stopping; calibration abandoned, retry")
            _, joints = check_capture(scan, self.settings.stillness.window_s)
            from registration.detection import detect_spheres

            volume = self.volumes.load(scan)
            if geometry is None:
                geometry = series_geometry(volume)
            det = detect_spheres(volume, det_params)
            q = self.nominal_model.check_joints(joints)
            robot_mm = sphere_centres_robot_mm(
                self.nominal_model, q, self.nominal_rod, self.phantom.centres_phantom_mm
            )
            out.append(
                match_pose(
                    f"scan {scan.id}",
                    q,
                    det.centres_image_mm,
                    robot_mm,
                    phantom=self.phantom,
                    series_uid=scan.series_uid,
                    frame_of_reference_uid=volume.frame_of_reference_uid,
                )
            )
            self._progress(
                cal_id, "detect", i, len(scans), scan_id=scan.id, n_matched=len(out[-1].sphere_indices)
            )
        return out, geometry

    def _finish_done(
        self,
        cal_id: int,
        scans: list[ScanRecord],
        matched: list[MatchedPose],
        result: Any,
        params: CalibrationParams,
        duration_s: float,
    ) -> None:
        folder = self.settings.data_dir / "calibrations" / str(cal_id)
        folder.mkdir(parents=True, exist_ok=True)
        urdf = write_calibrated_urdf(
            result.chain,
            folder / URDF_FILE,
            comment=f"oarmreg calibration {cal_id}: {int(result.used.sum())} poses, FrameOfReferenceUID "
            f"{matched[0].frame_of_reference_uid}, leave-one-pose-out mean {result.lopo_mean_mm:.3f} mm",
        )
        text = urdf.read_text(encoding="utf-8")
        doc = result.to_dict()
        chash = calibration_hash(text, doc["tool0_from_phantom"])
        doc["provenance"] = {
            "calibration_id": cal_id,
            "calibration_hash": chash,
            "software": f"oarmreg {__version__}",
            "robot_model": self.nominal_model.name,
            "nominal_urdf": str(self.nominal_model.urdf_path),
            "phantom": str(self.phantom.name),
            "params": dataclasses.asdict(params),
            "frame_of_reference_uid": matched[0].frame_of_reference_uid,
            "scans": [
                {"scan_id": s.id, "series_uid": s.series_uid, "joints_rad": [float(v) for v in m.joints_rad]}
                for s, m in zip(scans, matched, strict=True)
            ],
        }
        self.db.calibrations.finish(
            cal_id, status="done", duration_s=duration_s, result=doc, urdf_text=text,
            urdf_path=str(urdf), calibration_hash=chash,
        )  # fmt: skip
        log.info(
            "calibration %d done: %d poses, LOPO mean %.3f mm, predicted held-out %.3f mm RMS, %.1f s",
            cal_id, int(result.used.sum()), result.lopo_mean_mm, result.predicted_held_out_rms_mm, duration_s,
        )  # fmt: skip
        self.publish(
            CalibrationDone(
                calibration_id=cal_id,
                calibration_hash=chash,
                n_poses_used=int(result.used.sum()),
                leave_one_pose_out_mean_mm=doc["leave_one_pose_out_mean_mm"],
                predicted_held_out_rms_mm=doc["predicted_held_out_rms_mm"],
            )
        )

    def _finish_refused(self, cal_id: int, e: Exception, duration_s: float) -> None:
        title = title_of(e)
        self.db.calibrations.finish(
            cal_id, status="refused", duration_s=duration_s, reason=str(e), problem_title=title
        )
        log.warning("calibration %d refused (%s): %s", cal_id, title, e)
        self.publish(CalibrationRefused(calibration_id=cal_id, title=title, reason=str(e)))

    # ---- activation ----------------------------------------------------------------------

    def _model_of(self, rec: CalibrationRecord) -> tuple[RobotModel, NDArray[np.float64]]:
        """The calibrated model (URDF rewritten from the row if the file is gone) and rod."""
        assert rec.result is not None and rec.urdf_text is not None
        path = Path(rec.urdf_path or self.settings.data_dir / "calibrations" / str(rec.id) / URDF_FILE)
        if not path.is_file() or path.read_text(encoding="utf-8") != rec.urdf_text:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(rec.urdf_text, encoding="utf-8")
        return RobotModel.load(path), np.asarray(rec.result["tool0_from_phantom"], dtype=np.float64)

    @staticmethod
    def _ref(rec: CalibrationRecord) -> dict[str, Any]:
        return {
            "calibration_id": rec.id,
            "calibration_hash": rec.calibration_hash,
            "robot_urdf": rec.urdf_path,
            "predicted_chain_error_mm": (rec.result or {}).get("predicted_chain_error_mm"),
        }

    def activate(self, cal_id: int) -> tuple[CalibrationRecord, Activation]:
        """Use calibration ``cal_id`` from now on; retire the registrations (none current).

        Raises
        ------
        NotFoundError, CalibrationNotUsableError
        """
        rec = self.db.calibrations.get(cal_id)
        if rec is None:
            raise NotFoundError(f"calibration {cal_id} does not exist; GET /calibrations lists them")
        if rec.withdrawn_at is not None:
            raise CalibrationNotUsableError(
                f"calibration {cal_id} was withdrawn at {rec.withdrawn_at} ({rec.withdrawn_reason}); "
                "calibrate again with complete, unchanged scans"
            )
        if rec.status != "done":
            raise CalibrationNotUsableError(
                f"calibration {cal_id} is {rec.status}"
                + (f" ({rec.reason})" if rec.reason else "")
                + "; only a finished calibration can be activated"
            )
        model, rod = self._model_of(rec)
        act: Activation = self.orchestrator.use_calibration(
            model, rod, self._ref(rec), activate=lambda: self.db.calibrations.activate(cal_id)
        )
        log.warning(
            "calibration %d activated (%s); registrations %s retired, none current until the next /register",
            cal_id, rec.calibration_hash[:12], list(act.retired_registration_ids),
        )  # fmt: skip
        self.publish(
            CalibrationActivated(
                calibration_id=cal_id,
                calibration_hash=rec.calibration_hash,
                previous_calibration_id=act.previous_calibration_id,
            )
        )
        self.publish(
            RegistrationRetired(
                registration_ids=act.retired_registration_ids,
                previous_current_registration_id=act.previous_current_registration_id,
                calibration_id=cal_id,
                reason=f"calibration {cal_id} was activated; POST /register with a new scan",
            )
        )
        out = self.db.calibrations.get(cal_id)
        assert out is not None
        return out, act


@dataclass(frozen=True)
class CalibrationRefusal:
    """A calibration request refused at once: why, and the id of the ``refused`` record stored.
    Returned, not raised, so the id travels typed."""

    calibration_id: int
    error: OarmRegError


def _request_json(req: CalibrationRequest) -> dict[str, Any]:
    return {
        "scan_ids": None if req.scan_ids is None else list(req.scan_ids),
        "last": req.last,
        "parameter_set": req.parameter_set,
        "drop_weak": req.drop_weak,
        "max_condition": req.max_condition,
    }


def calibration_params(
    *,
    parameter_set: str = "full",
    drop_weak: bool = False,
    max_condition: float | None = None,
    estimator: str | None = None,
    max_predicted_error_mm: float | None = None,
    target_rms_mm: float | None = None,
) -> Any:
    """The one mapping from the CLI flags / the service's request fields to ``CalibrationParams``:
    ``oarmreg calibrate run``, ``POST /calibrations`` and ``oarmreg demo --calibrate`` all pass
    through here, so their defaults are :class:`registration.calibration.solver.CalibrationParams`'s."""
    from registration.calibration.records import (
        CalibrationParams,
    )

    extra: dict[str, Any] = {}
    if estimator is not None:
        extra["estimator"] = estimator
    if max_predicted_error_mm is not None:
        extra["max_predicted_error_mm"] = max_predicted_error_mm
    if target_rms_mm is not None:
        extra["target_rms_mm"] = target_rms_mm
    return CalibrationParams(
        parameter_set=parameter_set,  # type: ignore[arg-type]
        max_condition=max_condition,
        on_weak="drop" if drop_weak else "refuse",
        **extra,
    )
