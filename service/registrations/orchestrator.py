"""``POST /register`` and ``POST /verify``: resolve the scan → check its capture → run the pipeline
(:mod:`registration.pipeline`) → store → publish.

Each call runs on a worker thread (the API awaits it with ``anyio.to_thread``) under one
lock, so concurrent calls run one after the other and never interleave their writes.
Every outcome of ``register`` for a scan that exists is stored: a refusal (robot moved, joint
history incomplete, robot link down, too few spheres, ambiguous, FRE over the gate, bad scan, a
superseded scan, a scan that changed while it was registered, or a bug — an ``InternalError``,
answered 500) becomes a ``refused`` registration with its reason, problem title and HTTP status;
:meth:`Orchestrator.register` returns it as a :class:`RegistrationRefusal` (it is not raised; the
API answers problem details from it) and the previous current registration stays current.  Nothing
to register (no such scan, no complete scan) raises and stores nothing.

Which registration may be current is a rule (docs/safety.md, "Which registration may be current"):
a verification that fails its gate, or cannot be computed because the error is beyond what matching
can bridge, withdraws the registration it verified (never a calibration); a scan the service already
has newer evidence against (:meth:`service.store.registrations.RegistrationStore.supersession`) is
refused unless the request overrides it explicitly (audited by the API).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from drivers.errors import RobotLinkError
from registration import __version__
from registration.calibration.records import (
    chain_error_figure,
)
from registration.detection import params_for_spheres
from registration.errors import DicomSeriesError, OarmRegError, TooFewSpheresError
from registration.imaging.scan_geometry import series_geometry
from registration.matching.records import (
    RegistrationParams,
)
from registration.matching.verification import verify_registration
from registration.model.kinematics import RobotModel
from registration.model.phantom import Phantom
from registration.pipeline import PipelineParams, locate_spheres, register_scan
from service.error_map import http_status_of, title_of
from service.errors import (
    InternalError,
    NoCurrentRegistrationError,
    NoScanError,
    NotFoundError,
    SupersededScanError,
    VerificationRefusedError,
    VerificationUncomputableError,
)
from service.events import (
    CalibrationDeactivated,
    DerivedWithdrawn,
    Publish,
    RegistrationDone,
    RegistrationRefused,
    RegistrationRetired,
    RegistrationWithdrawn,
    VerificationDone,
)
from service.intake.volume_cache import VolumeCache
from service.records import (
    RegistrationRecord,
    RegistrationRefusal,
    ScanRecord,
    VerificationRecord,
    matrix4,
    points3,
)
from service.registrations.figures import provenance, registration_figures, verification_figures
from service.registrations.robot_side import FINGERPRINT_KEY, robot_settings_fingerprint, stale_reasons
from service.registrations.scan_checks import check_capture
from service.settings import Settings
from service.store import Database
from service.store.base import utc_now
from service.store.registrations import DerivedWithdrawal, Supersession

log = logging.getLogger(__name__)


def pipeline_params(settings: Settings, phantom: Phantom) -> PipelineParams:
    """The pipeline's parameters from the service settings."""
    ds, q = settings.detection, settings.quality
    detection = params_for_spheres(
        phantom.sphere_material, float(phantom.sphere_diameter_mm), use_mar=ds.use_mar
    )
    if ds.method != "default":
        detection = replace(detection, method=ds.method)
    return PipelineParams(
        detection=detection,
        registration=RegistrationParams(
            min_matched=q.min_matched_spheres,
            min_runner_up_margin=q.min_symmetry_margin,
            max_fre_mm=q.max_fre_mm,
        ),
        default_target_distance_mm=q.default_target_distance_mm,
    )


def _confirmed(params: PipelineParams) -> PipelineParams:
    """``params`` with the phantom file confirmed by the request (``phantom_confirmed``)."""
    return replace(params, registration=replace(params.registration, phantom_confirmed=True))


LikelyCause = Literal["cell-not-calibrated", "phantom-or-oarm-moved"]


@dataclass(frozen=True)
class VerificationWithdrawal:
    """Why nothing is current: a verification withdrew the registration (docs/safety.md).  What
    ``/registration/current`` (409), ``/ready`` and the page say, with the likely cause and the action."""

    registration_id: int
    verification_scan_id: int
    verification_id: int | None
    """None: the verification could not be computed (the error is beyond what matching can bridge)."""
    reason: str
    withdrawn_at: str
    predicted_chain_error_mm: float | None
    """The withdrawn registration's expected error at the robot's other poses."""
    calibrated: bool
    """Whether an active calibration backed that figure (else the nominal model's prior)."""
    gate_mm: float
    likely_cause: LikelyCause
    cause: str
    action: str

    def describe(self) -> str:
        return f"registration {self.registration_id} was withdrawn: {self.reason}. Likely cause: {self.cause}"


MOVED_ACTION = (
    "check the phantom's mount on the rod and the O-arm's placement, scan the phantom again and register "
    "the new scan"
)
"""What to do when the phantom or the O-arm moved (``likely_cause`` ``phantom-or-oarm-moved``)."""


def same_pose(a: Sequence[float] | None, b: Sequence[float] | None, tol_rad: float) -> bool:
    """Whether two joint vectors are the same pose within ``tol_rad`` (False when either is unknown)."""
    if a is None or b is None or len(a) != len(b):
        return False
    return bool(np.max(np.abs(np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64))) <= tol_rad)


def verification_withdrawal(
    rec: RegistrationRecord,
    gate_mm: float,
    *,
    verification_joints_rad: Sequence[float] | None = None,
    same_pose_tol_rad: float = 0.0,
) -> VerificationWithdrawal:
    """The likely cause of ``rec``'s withdrawal by a verification and what to do.

    At the registration scan's own joints (within ``same_pose_tol_rad``, the stillness tolerance) the
    chain's error is absorbed by the fit, so it cannot explain a failure: the phantom was knocked or
    the O-arm moved.  At another pose: cell not calibrated when the registration's own expected error
    at other poses (``predicted_chain_error_mm``) is at or above the gate (a verification at another
    pose is then expected to fail whatever else happened); otherwise the chain should have held, and
    again the phantom or the O-arm moved."""
    assert rec.withdrawn_by_scan is not None
    fig = rec.figures
    chain = None if fig is None else fig.predicted_chain_error_mm
    cal = None if fig is None else fig.provenance.get("calibration")
    calibrated = isinstance(cal, dict) and cal.get("calibration_id") is not None
    reg_joints = None if fig is None else fig.provenance.get("joints_rad")
    at_registration_pose = same_pose(verification_joints_rad, reg_joints, same_pose_tol_rad)
    if at_registration_pose:
        cause: LikelyCause = "phantom-or-oarm-moved"
        why = (
            "phantom knocked or O-arm moved since the registration scan: the verification scan was taken "
            "at the registration scan's own joints, where the robot model's and rod's errors are absorbed "
            "by the fit, so the robot side cannot explain it"
        )
        action = MOVED_ACTION
    elif chain is not None and chain >= gate_mm:
        backed = (
            f"calibration {cal['calibration_id']}'s posterior figure" if calibrated and isinstance(cal, dict)
            else "the nominal model's prior: the cell is not calibrated"
        )  # fmt: skip
        cause = "cell-not-calibrated"
        why = (
            f"cell not calibrated: the registration's expected error at the robot's other poses is "
            f"{chain:.2f} mm ({backed}), at or above the {gate_mm:g} mm gate, so a verification at "
            "another pose is expected to fail"
        )
        action = (
            "calibrate the cell (docs/calibration.md: POST /calibrations with a calibration session's "
            "scans), activate the calibration, then scan the phantom and register again"
        )
    else:
        cause = "phantom-or-oarm-moved"
        why = (
            "phantom knocked or O-arm moved since the registration scan (the registration's expected "
            f"error at other poses, {'unknown' if chain is None else f'{chain:.2f} mm'}, is below the "
            f"{gate_mm:g} mm gate)"
        )
        action = MOVED_ACTION
    return VerificationWithdrawal(
        registration_id=rec.id,
        verification_scan_id=rec.withdrawn_by_scan,
        verification_id=rec.withdrawn_by_verification,
        reason=rec.reason,
        withdrawn_at=rec.withdrawn_at or "",
        predicted_chain_error_mm=chain,
        calibrated=calibrated,
        gate_mm=gate_mm,
        likely_cause=cause,
        cause=why,
        action=action,
    )


@dataclass(frozen=True)
class SupersededOverride:
    """``POST /register`` with ``allow_superseded``: the reason the request gave (audited)."""

    reason: str


class Orchestrator:
    """Runs registrations and verifications; holds the current registration in memory."""

    def __init__(
        self,
        settings: Settings,
        db: Database,
        phantom: Phantom,
        robot_model: RobotModel,
        publish: Publish,
        volumes: VolumeCache | None = None,
    ) -> None:
        self.settings = settings
        self.db = db
        self.phantom = phantom
        self.robot_model = robot_model
        self.publish = publish
        self.volumes = volumes if volumes is not None else VolumeCache()
        self.config_hash = settings.config_hash()
        self.robot_settings = robot_settings_fingerprint(settings, robot_model)
        """The robot side the settings in force describe (service.registrations.robot_side)."""
        self.tool0_from_phantom = settings.robot.tool0_from_phantom.matrix()
        self._nominal: tuple[RobotModel, NDArray[np.float64], None] = (
            robot_model,
            self.tool0_from_phantom,
            None,
        )
        """The model and rod of the settings, used again when the active calibration is withdrawn."""
        self.params = pipeline_params(settings, phantom)
        self.calibration: dict[str, Any] | None = None
        """``{"calibration_id", "calibration_hash", "robot_urdf"}`` of the active calibration (None:
        the nominal model and rod of the settings); named in every registration's provenance."""
        self._lock = threading.Lock()
        restored = db.registrations.current()
        self._current: RegistrationRecord | None = None if restored is None else self.with_evidence(restored)
        self._withdrawn_by_verification: RegistrationRecord | None = (
            db.registrations.standing_verification_withdrawal()
        )
        """The registration a failed verification withdrew, while that is why nothing is current."""
        self.busy = False
        self.robot_side_withdrawal = ""
        """Why start-up withdrew the current registration (robot settings changed); ``/ready`` names it
        while nothing is current."""
        if self._current is not None:
            log.info(
                "restored current registration %d (scan %s, FRE %.3f mm)",
                self._current.id,
                self._current.series_uid,
                self._current.fre_mm or float("nan"),
            )

    def with_evidence(self, rec: RegistrationRecord) -> RegistrationRecord:
        """``rec`` with ``verified_by`` set when a verification at another pose passed against it."""
        if rec.figures is None:
            return rec
        reg_joints = rec.figures.provenance.get("joints_rad")
        tol = self.settings.stillness.max_deviation_rad
        for ver in self.db.verifications.passed_for(rec.id):
            if ver.figures.joints_rad is not None and not same_pose(ver.figures.joints_rad, reg_joints, tol):
                return replace(rec, verified_by=ver.id)
        return rec

    def withdraw_if_robot_side_changed(self) -> str:
        """At start-up, after the active calibration is restored: withdraw the current registration
        if it rests on other robot settings or another calibration than those in force (a restart
        after a rod change must not serve the old matrix).  Returns the reason ("" when it stands)."""
        with self._lock:
            cur = self._current
            if cur is None or cur.figures is None:
                return ""
            changed = stale_reasons(
                cur.figures.provenance, self.robot_settings, self.calibration, self.tool0_from_phantom
            )
            if not changed:
                return ""
            reason = (
                f"the robot side changed since registration {cur.id} was made ({', '.join(changed)}): "
                "its matrix no longer describes this robot; scan the phantom and register again"
            )
            self.db.registrations.withdraw_one(cur.id, reason)
            self._current = None
            self.robot_side_withdrawal = reason
            self._withdrawn_by_verification = None
        log.warning("registration %d not restored: %s", cur.id, reason)
        self.publish(RegistrationWithdrawn(
            registration_ids=(cur.id,), scan_id=cur.scan_id or 0, was_current=True, reason=reason,
        ))  # fmt: skip
        return reason

    @property
    def current(self) -> RegistrationRecord | None:
        """The current (accepted) registration record, or None (atomic reference read)."""
        return self._current

    @property
    def withdrawal(self) -> VerificationWithdrawal | None:
        """Why nothing is current when a verification withdrew the registration (None otherwise)."""
        w = self._withdrawn_by_verification
        if w is None or self._current is not None:
            return None
        return self._verification_withdrawal(w)

    def use_calibration(
        self,
        robot_model: RobotModel,
        tool0_from_phantom: NDArray[np.float64],
        calibration: dict[str, Any] | None,
        activate: Callable[[], Any] | None = None,
    ) -> Any:
        """Register and verify with this model and rod from now on (waits for a running registration).

        ``activate`` runs under the same lock (the store's activation: it retires the registrations
        and clears the current pointer); then nothing is current until the next ``/register``.
        Returns what ``activate`` returned.
        """
        with self._lock:
            out = activate() if activate is not None else None
            self.robot_model, self.tool0_from_phantom, self.calibration = (
                robot_model, tool0_from_phantom, calibration,
            )  # fmt: skip
            if activate is not None:
                self._current = None
                self._withdrawn_by_verification = None  # the action it asked for may be this one
            return out

    @property
    def no_current_reason(self) -> str:
        """Why nothing is current: the newest withdrawal's reason if that is why, else ``""``."""
        if self._current is not None:
            return ""
        v = self.withdrawal
        if v is not None:
            return v.describe()
        w = self.db.registrations.latest_withdrawn()
        r = self.db.registrations.latest_retired()
        if r is not None and (w is None or (r.retired_at or "") >= (w.withdrawn_at or "")):
            # the newest end of a current registration was a calibration's activation, not the
            # withdrawal (which a later registration outlived)
            return (
                f"registration {r.id} was retired when calibration {r.retired_by_calibration} was "
                "activated (it was made with the previous robot model); register a new scan"
            )
        return "" if w is None else f"registration {w.id} was withdrawn: {w.reason}"

    def withdraw_scan(self, scan_id: int, reason: str) -> list[int]:
        """Withdraw the registrations made from ``scan_id`` (design §9: its scan turned out incomplete
        or damaged).  Waits for a registration in progress; if the current one is withdrawn nothing is
        current afterwards (every push channel INVALID).  Publishes ``registration_withdrawn``."""
        with self._lock:
            ids, was_current = self.db.registrations.withdraw_for_scan(scan_id, reason)
            if was_current or (self._current is not None and self._current.id in ids):
                self._current = None
                self._withdrawn_by_verification = None  # this withdrawal is the newer reason
            derived = self.db.registrations.withdraw_derived(scan_id, reason)
            if derived.deactivated_calibration_id is not None:  # back to the nominal model and rod
                self.robot_model, self.tool0_from_phantom, self.calibration = self._nominal
                self._current = None
        vers, cals = list(derived.verification_ids), list(derived.calibration_ids)
        if vers or cals:
            log.warning(
                "scan %d: verification(s) %s and calibration(s) %s withdrawn: %s", scan_id, vers, cals, reason
            )
            self.publish(
                DerivedWithdrawn(
                    scan_id=scan_id, verification_ids=tuple(vers), calibration_ids=tuple(cals), reason=reason
                )
            )
        if ids:
            log.warning(
                "registration(s) %s withdrawn (scan %d)%s: %s",
                ", ".join(map(str, ids)), scan_id, " (the current one among them)" if was_current else "",
                reason,
            )  # fmt: skip
            self.publish(
                RegistrationWithdrawn(
                    registration_ids=tuple(ids), scan_id=scan_id, was_current=was_current, reason=reason
                )
            )
        if derived.deactivated_calibration_id is not None:
            self._publish_deactivation(derived, reason)
        return ids

    def _publish_deactivation(self, derived: DerivedWithdrawal, reason: str) -> None:
        cal_id = derived.deactivated_calibration_id
        assert cal_id is not None  # the caller checked
        why = (
            f"the active calibration {cal_id} was withdrawn ({reason}); the nominal robot model is used "
            "again: recalibrate, or activate another calibration, then POST /register with a new scan"
        )
        log.warning("%s; registrations %s retired", why, list(derived.retired_registration_ids))
        self.publish(CalibrationDeactivated(calibration_id=cal_id, reason=why))
        self.publish(
            RegistrationRetired(
                registration_ids=derived.retired_registration_ids,
                previous_current_registration_id=None,
                calibration_id=cal_id,
                reason=why,
            )
        )

    def wait_idle(self) -> None:
        """Return once no registration or verification is running."""
        with self._lock:
            pass

    def _resolve_scan(self, scan_id: int | None) -> ScanRecord:
        if scan_id is None:
            scan = self.db.scans.latest_complete()
            if scan is None:
                raise NoScanError(
                    f"no complete scan has arrived in {self.settings.watch_dir} yet; export the O-arm scan "
                    "there (GET /scans lists what the watcher has seen)"
                )
            return scan
        found = self.db.scans.get(scan_id)
        if found is None:
            raise NotFoundError(f"scan {scan_id} does not exist; GET /scans lists the recorded scans")
        return found

    # ---- register -------------------------------------------------------------------------

    def register(
        self,
        scan_id: int | None = None,
        targets_image_mm: Sequence[Sequence[float]] | None = None,
        *,
        override: SupersededOverride | None = None,
        phantom_confirmed: bool = False,
    ) -> RegistrationRecord | RegistrationRefusal:
        """Run the pipeline; return the stored accepted record, or the refusal (stored too, as
        ``refused``, its record id in :attr:`RegistrationRefusal.registration_id`; a bug is an
        :class:`~service.errors.InternalError` refusal, answered 500).

        A scan the service has newer evidence against is refused (:class:`SupersededScanError`)
        unless ``override`` is given; then the accepted record's provenance names what was overridden
        and why (``superseded_override``).

        Raises
        ------
        NotFoundError, NoScanError
            Nothing to register (not stored).
        """
        with self._lock:
            self.busy = True
            try:
                return self._register_locked(scan_id, targets_image_mm, override, phantom_confirmed)
            finally:
                self.busy = False

    def _register_locked(
        self,
        scan_id: int | None,
        targets_image_mm: Sequence[Sequence[float]] | None,
        override: SupersededOverride | None,
        phantom_confirmed: bool = False,
    ) -> RegistrationRecord | RegistrationRefusal:
        scan = self._resolve_scan(scan_id)
        superseded = self.db.registrations.supersession(scan.id, scan.frame_of_reference_uid)
        t0 = time.perf_counter()
        snap = scan.snapshot
        draft = RegistrationRecord(
            created_at=utc_now(),
            status="refused",
            config_hash=self.config_hash,
            software_version=__version__,
            scan_id=scan.id,
            series_uid=scan.series_uid,
            targets_image_mm=None if targets_image_mm is None else points3(targets_image_mm),
            joints_rad=None if snap is None else snap.joints_rad,
            joints_received_at=None if snap is None else snap.joints_received_at,
        )
        if superseded is not None and override is None:
            return self._store_refusal(draft, superseded_error(scan, superseded), t0)
        try:
            accepted = self._compute(scan, draft, targets_image_mm, phantom_confirmed)
            if superseded is not None and override is not None:
                accepted = _overridden(accepted, superseded, override)
        except (OarmRegError, RobotLinkError) as e:
            return self._store_refusal(draft, e, t0)
        except Exception as e:  # a bug: store it as refused, answer 500
            log.exception("registration of scan %d failed unexpectedly", scan.id)
            err = InternalError(
                f"registration of scan {scan.id} failed unexpectedly: {type(e).__name__}: {e}"
            )
            err.__cause__ = e
            return self._store_refusal(draft, err, t0)
        now = self.db.scans.get(scan.id)
        if now is None or now.status != "complete":
            changed = DicomSeriesError(
                f"scan {scan.id} (series {scan.series_uid}) changed while it was being registered "
                f"(now {None if now is None else now.status}: {None if now is None else now.reason}); "
                "register it again once it is complete"
            )
            return self._store_refusal(draft, changed, t0)
        reg_id = self.db.registrations.insert(
            replace(accepted, duration_s=time.perf_counter() - t0), make_current=True
        )
        stored = self.db.registrations.get(reg_id)
        assert stored is not None and stored.figures is not None
        self._current = stored
        self._withdrawn_by_verification = None
        log.info(
            "registration %d accepted: scan %d (series %s), FRE %.3f mm, %d/%d spheres matched, %.2f s",
            reg_id, scan.id, scan.series_uid, stored.fre_mm, stored.figures.n_matched,
            stored.figures.n_expected, stored.duration_s,
        )  # fmt: skip
        self.publish(
            RegistrationDone(
                registration_id=reg_id,
                scan_id=scan.id,
                series_uid=scan.series_uid,
                fre_mm=stored.fre_mm,
                n_matched=stored.figures.n_matched,
            )
        )
        return stored

    def _compute(
        self,
        scan: ScanRecord,
        draft: RegistrationRecord,
        targets_image_mm: Sequence[Sequence[float]] | None,
        phantom_confirmed: bool = False,
    ) -> RegistrationRecord:
        """Check the capture, load, run the pipeline; the accepted record (not stored yet)."""
        snap, joints_rad = check_capture(scan, self.settings.stillness.window_s)
        t = time.perf_counter()
        volume = self.volumes.load(scan)
        load_s = time.perf_counter() - t
        run = register_scan(
            volume,
            joints_rad,
            self.robot_model,
            self.tool0_from_phantom,
            self.phantom,
            _confirmed(self.params) if phantom_confirmed else self.params,
            targets_image_mm=targets_image_mm or None,
        )
        source = (
            "request"
            if run.targets_given
            else (
                f"default: {self.params.default_target_distance_mm:g} mm from the phantom centre "
                "along ±x, ±y, ±z of the robot frame"
            )
        )
        prov = provenance(
            scan,
            snap,
            robot_model=self.settings.robot.model,
            tool0_from_phantom=self.tool0_from_phantom,
            phantom=self.phantom,
            config_hash=self.config_hash,
        )
        prov["calibration"] = self.calibration
        prov[FINGERPRINT_KEY] = self.robot_settings
        chain_mm, chain_src = chain_error_figure(self.calibration)
        figures = registration_figures(
            run,
            self.phantom,
            targets_source=source,
            provenance=prov,
            load_s=load_s,
            predicted_chain_error_mm=chain_mm,
            chain_error_source=chain_src,
            series_geometry=series_geometry(volume).to_dict(),
        )
        return replace(
            draft,
            status="accepted",
            image_from_robot=matrix4(np.asarray(run.result.image_from_robot, dtype=np.float64).tolist()),
            fre_mm=float(run.result.fre_mm),
            figures=figures,
        )

    def _store_refusal(
        self, draft: RegistrationRecord, e: OarmRegError | RobotLinkError, t0: float
    ) -> RegistrationRefusal:
        title = title_of(e)
        record = replace(
            draft,
            status="refused",
            reason=str(e),
            problem_title=title,
            http_status=http_status_of(e),
            duration_s=time.perf_counter() - t0,
        )
        try:
            reg_id = self.db.registrations.insert(record, make_current=False)
        except Exception:
            log.exception("could not store the refused registration of scan %s", record.scan_id)
            return RegistrationRefusal(None, e)
        log.warning("registration %d refused (%s): %s", reg_id, title, e)
        self.publish(
            RegistrationRefused(
                registration_id=reg_id,
                scan_id=record.scan_id,
                series_uid=record.series_uid,
                title=title,
                reason=str(e),
            )
        )
        return RegistrationRefusal(reg_id, e)

    # ---- verify ---------------------------------------------------------------------------

    def verify(self, scan_id: int | None = None) -> VerificationRecord:
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

    def _verify_locked(self, scan_id: int | None) -> VerificationRecord:
        current = self._current
        if current is None or current.image_from_robot is None:
            raise NoCurrentRegistrationError(
                "there is no current registration to verify; POST /register first"
            )
        scan = self._resolve_scan(scan_id)
        if current.scan_id is not None and scan.id <= current.scan_id:
            raise VerificationRefusedError(
                f"scan {scan.id} is not newer than scan {current.scan_id} of the current registration "
                f"{current.id}; move the robot, scan again and verify against that scan"
            )
        snap, joints_rad = check_capture(scan, self.settings.stillness.window_s)
        spheres = locate_spheres(
            self.volumes.load(scan), joints_rad, self.robot_model, self.tool0_from_phantom, self.phantom,
            self.params.detection,
        )  # fmt: skip
        image_from_robot = np.asarray(current.image_from_robot, dtype=np.float64)
        try:
            res = verify_registration(
                image_from_robot, spheres.robot_mm, spheres.image_mm, params=self.params.registration
            )
        except TooFewSpheresError as e:
            if len(spheres.image_mm) < self.params.registration.min_matched:
                raise  # the scan shows too few spheres: evidence about the scan, not the registration
            raise self._withdraw_uncomputable(current, scan, e) from e
        gate = self.settings.quality.max_verification_error_mm
        record = VerificationRecord(
            created_at=utc_now(),
            registration_id=current.id,
            scan_id=scan.id,
            series_uid=scan.series_uid,
            passed=float(res.max_mm) <= gate,
            mean_mm=float(res.mean_mm),
            rms_mm=float(res.rms_mm),
            max_mm=float(res.max_mm),
            figures=verification_figures(spheres, res, self.phantom, gate_mm=gate, snap=snap),
            config_hash=self.config_hash,
            software_version=__version__,
        )

        def withdraw_reason(ver_id: int) -> str:
            return (
                f"verification {ver_id} (scan {scan.id}) failed its gate: max {record.max_mm:.3f} mm > "
                f"{gate:g} mm (quality.max_verification_error_mm)"
            )

        ver_id = self.db.verifications.insert(record, withdraw_reason=withdraw_reason)
        if not record.passed:
            self._current = None
        elif current.verified_by is None:  # at another pose, it upgrades the evidence to "verified"
            self._current = self.with_evidence(current)
        self._write_histogram(
            ver_id, scan.id, current.id, np.asarray(res.errors_mm, dtype=np.float64), gate_mm=gate
        )
        stored = self.db.verifications.get(ver_id)
        assert stored is not None
        self.publish(
            VerificationDone(
                verification_id=ver_id,
                registration_id=current.id,
                scan_id=scan.id,
                mean_mm=record.mean_mm,
                max_mm=record.max_mm,
                passed=record.passed,
            )
        )
        if not record.passed:
            self._published_withdrawal(current.id, withdraw_reason(ver_id))
        return stored

    def _withdraw_uncomputable(
        self, current: RegistrationRecord, scan: ScanRecord, e: TooFewSpheresError
    ) -> VerificationUncomputableError:
        """Withdraw ``current``: its verification on ``scan`` could not be computed (the spheres lie
        beyond what matching can bridge); the error to raise."""
        reason = f"the verification of scan {scan.id} could not be computed ({e})"
        self.db.registrations.withdraw_for_verification(
            current.id, reason, scan_id=scan.id, verification_id=None
        )
        self._current = None
        w = self._published_withdrawal(current.id, reason)
        return VerificationUncomputableError(
            f"{reason}; registration {current.id} is withdrawn: likely cause: {w.cause}; {w.action}"
        )

    def _verification_withdrawal(self, rec: RegistrationRecord) -> VerificationWithdrawal:
        """:func:`verification_withdrawal` with the joints of the verification scan (its record's, or
        the scan's snapshot when it could not be computed)."""
        joints: Sequence[float] | None = None
        ver = (
            None
            if rec.withdrawn_by_verification is None
            else self.db.verifications.get(rec.withdrawn_by_verification)
        )
        if ver is not None:
            joints = ver.figures.joints_rad
        elif rec.withdrawn_by_scan is not None:
            scan = self.db.scans.get(rec.withdrawn_by_scan)
            snap = None if scan is None else scan.snapshot
            joints = None if snap is None else snap.joints_rad
        return verification_withdrawal(
            rec,
            self.settings.quality.max_verification_error_mm,
            verification_joints_rad=joints,
            same_pose_tol_rad=self.settings.stillness.max_deviation_rad,
        )

    def _published_withdrawal(self, reg_id: int, reason: str) -> VerificationWithdrawal:
        """After the store withdrew ``reg_id`` (the current one) by a verification: remember why, log,
        publish ``registration_withdrawn`` (the push channels read :attr:`current`, now None)."""
        rec = self.db.registrations.get(reg_id)
        assert rec is not None and rec.withdrawn_by_scan is not None and rec.scan_id is not None
        self._withdrawn_by_verification = rec
        w = self._verification_withdrawal(rec)
        log.warning("%s; nothing is current; %s", w.describe(), w.action)
        self.publish(
            RegistrationWithdrawn(
                registration_ids=(reg_id,),
                scan_id=rec.scan_id,
                was_current=True,
                reason=reason,
                verification_scan_id=w.verification_scan_id,
                verification_id=w.verification_id,
            )
        )
        return w

    def _write_histogram(
        self, ver_id: int, scan_id: int, reg_id: int, errors_mm: NDArray[np.float64], *, gate_mm: float
    ) -> None:
        """The verification's histogram PNG; a failure is logged, the verification stays stored."""
        png = self.settings.data_dir / "histograms" / f"verification-{ver_id}.png"
        try:
            title = f"Verification {ver_id}: scan {scan_id} vs registration {reg_id}"
            write_histogram(errors_mm, png, title=title, gate_mm=gate_mm)
            self.db.verifications.set_histogram(ver_id, str(png))
        except Exception:
            log.exception("verification %d: writing the histogram %s failed", ver_id, png)


def superseded_error(scan: ScanRecord, why: Supersession) -> SupersededScanError:
    """The refusal of registering ``scan`` (docs/safety.md, "Which registration may be current")."""
    if why.rule == "withdrawn":
        msg = (
            f"scan {scan.id} may not be registered again: {why.detail}, so its matrix is known to be "
            f"wrong; check the phantom's mount and the O-arm, scan again and register the new scan"
        )
    else:
        msg = (
            f"scan {scan.id} is superseded: {why.detail} (FrameOfReferenceUID "
            f"{scan.frame_of_reference_uid}); register scan {why.scan_id} or a new scan instead"
        )
    return SupersededScanError(
        f"{msg} (to make scan {scan.id}'s registration current anyway, send allow_superseded: true with "
        "a reason; it is audited)",
        newer_scan_id=why.scan_id,
        rule=why.rule,
    )


def _overridden(
    accepted: RegistrationRecord, why: Supersession, override: SupersededOverride
) -> RegistrationRecord:
    """``accepted`` with the override named in its provenance (stored with the record)."""
    assert accepted.figures is not None
    prov = {
        **accepted.figures.provenance,
        "superseded_override": {
            "rule": why.rule, "newer_scan_id": why.scan_id, "detail": why.detail, "reason": override.reason,
        },
    }  # fmt: skip
    log.warning(
        "scan %s registered although superseded (%s), by request: %s", accepted.scan_id, why.detail,
        override.reason,
    )  # fmt: skip
    return replace(accepted, figures=replace(accepted.figures, provenance=prov))


def write_histogram(
    errors_mm: NDArray[np.float64], path: Path, *, title: str, gate_mm: float | None = None
) -> None:
    """Histogram of per-sphere position errors as a PNG (Bai 2018 fig. 7), via
    :mod:`service.registrations.histogram`;
    with ``gate_mm`` the gate line and PASS / FAIL."""
    from service.registrations.histogram import write_error_histogram

    path.parent.mkdir(parents=True, exist_ok=True)
    write_error_histogram(errors_mm, path, title=title, gate_mm=gate_mm)
