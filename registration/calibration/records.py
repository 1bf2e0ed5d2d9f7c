"""The calibration's records: its settings, the priors on the robot's geometric errors, one matched
pose, one fitted parameter, the result with its predicted figures, and its refusals.

:mod:`registration.calibration.solver` fills them; the service stores and serves them.  The priors'
widths and their origins are in docs/calibration.md ("Priors")."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Final, Literal

import numpy as np
from numpy.typing import NDArray

from registration import __version__
from registration.arrays import F64
from registration.calibration.targets import TARGET_RMS_MM
from registration.calibration.urdf import SerialChain

if TYPE_CHECKING:
    pass


I64 = NDArray[np.int64]


NOMINAL_CHAIN_ERROR_MM: Final = 1.0
"""``predicted_chain_error_mm`` of a registration made with the nominal model and rod (no active
calibration): 1.03 mm mean held-out error of the nominal model was measured on a simulated TX60
cell it was not tuned on; the test bed's nominal model gives 1.0–1.4 mm at error scale 1
(``python -m benchmarks.bench_calibration``)."""


DROP_CONDITION: Final = 100.0
"""``--drop-weak`` drops until the condition number is ≤ this when no ``max_condition`` is given
(Schroer et al. via Nahvi & Hollerbach 1996, research/calibration.md §1)."""


MIN_POSES: Final = 6
"""K ≥ 6 scans per session: fewer leave the 18 robot + 12 hand-eye parameters barely determined."""


@dataclass(frozen=True)
class Priors:
    """Gaussian prior widths (σ per component) of the robot's geometric errors (docs/calibration.md).

    Origin: research/calibration.md §1 — an uncalibrated Stäubli TX60 is off by 0.312 mm / 0.221°
    on average (robotinfo.org summary of a published BAS-PSO study).  σ 0.1 mm per axis on each of
    the 7 joint origins with 0.01° tilts and zero offsets gives a nominal position error of that
    size at the flange (the test bed's error scale 1: ``benchmarks/calib_testbed.py``); the issue
    #10 cell (0.12 mm / 0.012°, TX60 study) is 1.2 × these.  The rod and the O-arm placement
    have no prior (flat): every pose sees them in full.
    """

    origin_translation_mm: float = 0.1
    """σ of a joint origin's shift / slide (mm)."""
    origin_rotation_deg: float = 0.01
    """σ of a joint origin's tilt (deg)."""
    zero_offset_deg: float = 0.01
    """σ of a joint's zero offset (deg)."""

    rod_translation_mm: float = 1.0
    rod_rotation_deg: float = 0.5
    """σ per axis of the rod about its CAD pose, for the posterior only (the fit leaves it free):
    the unseen test cell's rod was off 0.8 mm / 0.4° in all; 1 mm / 0.5° per axis covers it."""
    placement_translation_mm: float = 1000.0
    placement_rotation_deg: float = 90.0
    """σ of the O-arm placement, for the posterior only: effectively flat (the O-arm can stand
    anywhere), finite so a direction the poses cannot see gets a huge, not an infinite, variance."""

    def sigma_posterior(self, p: Parameter) -> float:
        """σ of ``p`` (rad or mm) in the posterior: :meth:`sigma`, the rod's and the placement's."""
        if p.group == "tool0_from_phantom":
            return self.rod_translation_mm if p.kind == "trans" else math.radians(self.rod_rotation_deg)
        if p.group == "image_from_robot":
            return (
                self.placement_translation_mm
                if p.kind == "trans"
                else math.radians(self.placement_rotation_deg)
            )
        return self.sigma(p)

    def sigma(self, p: Parameter) -> float:
        """σ of parameter ``p`` in its unit (rad or mm); inf for the rod and the placement."""
        if p.group in ("image_from_robot", "tool0_from_phantom"):
            return math.inf
        if p.kind == "trans":
            return self.origin_translation_mm
        deg = self.zero_offset_deg if p.name.endswith(" offset") else self.origin_rotation_deg
        return math.radians(deg)


PRIORS: Final = Priors()


@dataclass(frozen=True)
class CalibrationParams:
    """Settings of :func:`calibrate` (lengths in mm)."""

    parameter_set: Literal["full", "offsets", "hand-eye", "all"] = "full"
    estimator: Literal["map", "ls"] = "ls"
    """``"ls"``: robust least squares over the minimal complete set, no prior; ``"map"``: maximum a
    posteriori with Gaussian priors (:data:`PRIORS`) on all 6 error components of every joint
    origin (``parameter_set="full"`` becomes ``"all"``), their weight chosen by cross-validation
    over poses.  Default ``"ls"``: on the calibration test bed (tuning seeds 1–3 × error scales 1, 2
    × random / planned poses) MAP with CV gave 1.015 × the LS held-out mean (fixed prior scale 2:
    0.98 ×) — a tie, so the simpler, faster one; the refusal is on the predicted error either way,
    not on the condition number (docs/calibration.md)."""
    max_condition: float | None = None
    """Optional extra refusal on the condition number of the column-normalised identification
    Jacobian (data only, no prior).  Off by default: a parameter that moves nothing in the
    working volume is harmless, the refusal is on :attr:`max_predicted_error_mm`.  Schroer et al.
    (quoted in Nahvi & Hollerbach, ICRA 1996; research/calibration.md §1) ask < 100."""
    on_weak: Literal["refuse", "drop"] = "refuse"
    """``"drop"`` (``--drop-weak``): fix the weakest robot parameters at nominal until the condition
    number is ≤ ``max_condition`` (:data:`DROP_CONDITION` when that is None)."""
    prior_scales: tuple[float, ...] = (0.25, 0.5, 1.0, 2.0, 4.0, 8.0)
    """Multipliers of the prior widths tried by cross-validation (MAP); the one with the least
    mean squared prediction error on the left-out poses wins.  0.25–8 × spans an unseen cell's
    errors from a quarter of the priors to 8 × (the test bed sweeps 0.5–2 ×)."""
    cv_folds: int = 5
    """Folds of the cross-validation over poses (each fold leaves out every 5th pose)."""
    data_sd_mm: float = 0.05
    """Reference σ (mm) per residual component the prior weight is written against: σ_d / (s σ_j)
    per parameter.  0.05 mm ≈ FLE 0.07 mm 3-D / √3 plus unmodelled (sag, repeatability) of the
    DICOM calibration session; the cross-validated scale s absorbs any mismatch."""
    working_margin_mm: float = 40.0
    """Working volume = the scan volume grown by this (radius and half-length, mm): navigation
    uses the arm beyond the phantom's calibration positions — the phantom is 60 mm across and a
    target 150 mm from it (the registration's TRE targets) sits up to ~40 mm outside the volume
    when the phantom is at its edge.  The prediction and the refusal are over this volume."""
    unmodelled_floor_mm: float = 0.04
    """*Prior* RMS per-pose error (mm, 3-D) no geometric model has — compliance/sag, backlash,
    repeatability: what the planner assumes before any scan exists, and what the calibration
    falls back to (or widens to) when its poses cannot measure it (:attr:`unmodelled_source`,
    docs/calibration.md "Predicted error").  Origin: Stäubli TX60 repeatability ± 0.02 mm
    [unverified datasheet value] and non-geometric errors ≈ 10 % of the position error (Klimchik
    et al., research/calibration.md §1) of the TX60's 0.31 mm nominal error:
    √(0.02² + 0.031²) ≈ 0.04 mm."""
    unmodelled_source: Literal["leave-one-pose-out", "prior"] = "leave-one-pose-out"
    """Where the calibration's unmodelled per-pose error comes from: ``"leave-one-pose-out"``
    measures it on the session's own held-out residuals (:func:`registration.calibration.
    prediction.loo_unmodelled`: the rigid part of each pose's leave-one-pose-out residual beyond
    what detection noise and the other poses' errors explain, plus :attr:`unmodelled_se_factor`
    standard errors; the prior :attr:`unmodelled_floor_mm` where it cannot); ``"prior"`` takes
    max(in-sample residual, :attr:`unmodelled_floor_mm`) (the simpler, older estimate)."""
    unmodelled_se_factor: float = 1.0
    """Standard errors added to the leave-one-pose-out estimate of u² (mm²): the prediction uses
    its one-sided 84 % upper bound, so few poses (a wide estimate) widen the prediction instead of
    shrinking it.  1 is the convention for "one standard error", not tuned on the test bed."""
    repeatability_rms_mm: float = 0.0096
    """Least 3-D RMS of the error every sphere of one scan shares (the arm's repeatability: each
    move lands slightly elsewhere), used in the covariance's sandwich when the residuals show less.
    They cannot show it with ~10 poses: the fit absorbs ~¾ of it at its own poses and the detection
    noise's leak into a pose's rigid residual is larger than the rest (docs/calibration.md,
    "Which side it misses on").  Origin: Stäubli TX60 repeatability ± 0.02 mm (unconfirmed
    datasheet figure, research/staubli-link.md §5), read as ISO 9283 RP = l̄ + 3 S_l of the
    distances to the barycentre.  For an isotropic Gaussian scatter of σ per axis that is 3.62 σ,
    so the 3-D RMS √3 σ = 0.479 RP = 0.0096 mm."""
    farthest_split: bool = False
    """Scale the posterior by how optimistic it was on the poses farthest from the rest (≥ 1).
    Off by default: with 10 poses the ⌈K/4⌉ held-out poses make a noisy factor (1–15 on the
    tuning seeds), which pushed predicted / measured above 1.5 on 4 of 12 sets, against 1 without."""
    max_predicted_error_mm: float = 0.5
    """Refuse when the predicted RMS sphere error at the worst pose of the working volume exceeds
    this (mm).  0.5 mm: research/calibration.md §6 suggested gate on predicted TRE, half the
    ≈ 1 mm the nominal model gives (docs/calibration.md)."""
    min_poses: int = MIN_POSES
    target_rms_mm: float = TARGET_RMS_MM
    """The planner's target (``calibration.target_rms_mm``): the result says whether its predicted
    RMS over the working volume meets it (it is not a refusal; ``max_predicted_error_mm`` is)."""
    robust_scale_mm: float = 0.2
    """soft-L1 loss scale: residuals ≫ this (a wrong match, ≥ 1 mm) weigh linearly, not squared;
    true-cell residuals after calibration are ≈ 0.05 mm."""
    outlier_factor: float = 4.0
    """A pose whose RMS residual exceeds this × the median pose RMS (and the floor) is an outlier."""
    outlier_floor_mm: float = 0.25
    """... never flag below this RMS (0.25 mm: research note §6 residual RMS gate)."""
    outliers: Literal["exclude", "refuse"] = "exclude"
    leave_one_out: bool = True
    rank_rtol: float = 1e-7
    """Singular values below this × the largest count as zero for the numeric rank (they come from
    the normal matrix, whose round-off floor is ~1e-8 of the largest singular value)."""


@dataclass(frozen=True, eq=False)
class MatchedPose:
    """One calibration scan with its spheres matched to the phantom.

    Attributes
    ----------
    name : str
        Scan name for messages (e.g. its folder).
    joints_rad : ndarray, shape (n,)
        Reported joint angles.
    sphere_indices : ndarray, shape (K,), int
        Phantom sphere index of each matched centre.
    centres_image_mm : ndarray, shape (K, 3)
        Detected centres (image frame, LPS mm), paired with ``sphere_indices``.
    series_uid, frame_of_reference_uid : str
    """

    name: str
    joints_rad: F64
    sphere_indices: I64
    centres_image_mm: F64
    series_uid: str = ""
    frame_of_reference_uid: str = ""


@dataclass(frozen=True)
class Parameter:
    """One candidate parameter: a rotation about / translation along ``direction`` of a frame."""

    name: str
    group: str
    """``"image_from_robot"``, ``"tool0_from_phantom"`` or a joint name (its origin)."""
    kind: Literal["rot", "trans"]
    direction: tuple[float, float, float]

    @property
    def unit(self) -> str:
        return "rad" if self.kind == "rot" else "mm"


@dataclass(frozen=True, eq=False)
class CalibrationResult:
    """Outcome of :func:`calibrate` (mm, rad; see :meth:`to_dict` for the JSON form)."""

    image_from_robot: F64
    tool0_from_phantom: F64
    chain: SerialChain
    parameters: tuple[Parameter, ...]
    values: F64
    std_errors: F64
    rank: int
    condition_number: float
    singular_values: F64
    dropped: tuple[str, ...]
    pose_names: tuple[str, ...]
    used: NDArray[np.bool_]
    pose_rms_mm: F64
    pose_max_mm: F64
    sphere_residuals_mm: tuple[F64, ...]
    sphere_indices: tuple[I64, ...]
    """Phantom sphere index of each entry of ``sphere_residuals_mm``, per pose."""
    outliers: tuple[str, ...]
    lopo_pose_mean_mm: F64
    lopo_pose_rms_mm: F64
    timings_s: dict[str, float]
    fit_rms_mm: float
    fle_rms_mm: float
    """Per-sphere detection error (RMS, 3-D) implied by the residuals, corrected for the fitted DoF."""
    registration_tre_rms_mm: float
    """Fitzpatrick's RMS TRE over the phantom's spheres of a one-scan registration with this FLE and
    all spheres (1998 eq. 46): what re-registering after the O-arm moved adds."""
    estimator: str = "map"
    prior_scale: float = float("nan")
    """Multiplier of the prior widths chosen by cross-validation over poses (NaN for ``"ls"``)."""
    cv_scores: dict[float, float] | None = None
    """Prior scale → mean squared left-out sphere error (mm²) of the cross-validation."""
    posterior_cov: F64 | None = None
    """(P, P) posterior covariance of ``values`` (rad, mm)."""
    unmodelled_rms_mm: float = float("nan")
    """The per-pose unmodelled error (mm, 3-D RMS) the prediction used; where it came from is in
    :attr:`unmodelled`."""
    prediction: WorkingPrediction | None = None
    working_volume: dict[str, Any] | None = None
    target_rms_mm: float = TARGET_RMS_MM
    """The planner's target the prediction is compared with (``CalibrationParams.target_rms_mm``)."""
    unmodelled: UnmodelledEstimate | None = None
    """How :attr:`unmodelled_rms_mm` was estimated (source, the held-out figure, its standard error)."""

    @property
    def predicted_held_out_rms_mm(self) -> float:
        """Expected RMS sphere-centre error at a pose of the working volume after a one-scan
        registration with the calibrated model: the posterior propagated through the kinematics
        (docs/calibration.md); without a prediction the LOPO figure :attr:`lopo_predicted_rms_mm`."""
        if self.prediction is not None:
            return self.prediction.rms_mm
        return self.lopo_predicted_rms_mm

    @property
    def predicted_chain_error_mm(self) -> float:
        """The chain figure every registration with this calibration carries (RMS over the
        working volume, see :attr:`predicted_held_out_rms_mm`)."""
        return self.predicted_held_out_rms_mm

    @property
    def lopo_predicted_rms_mm(self) -> float:
        """Leave-one-pose-out figure: √(LOPO TRE² + registration TRE²); sees only poses like the others."""
        return math.sqrt(self.lopo_tre_rms_mm**2 + self.registration_tre_rms_mm**2)

    @property
    def lopo_tre_rms_mm(self) -> float:
        """Leave-one-pose-out error with the held-out scan's own detection error removed:
        √(mean LOPO RMS² − FLE²).  It estimates how far the calibrated model's prediction at an
        unseen pose is from where the spheres really are (not from where they are detected)."""
        v = self.lopo_pose_rms_mm[np.isfinite(self.lopo_pose_rms_mm)]
        if not v.size:
            return float("nan")
        return math.sqrt(max(float(np.mean(v**2)) - self.fle_rms_mm**2, 0.0))

    @property
    def lopo_mean_mm(self) -> float:
        v = self.lopo_pose_mean_mm[np.isfinite(self.lopo_pose_mean_mm)]
        return float(v.mean()) if v.size else float("nan")

    @property
    def lopo_max_mm(self) -> float:
        v = self.lopo_pose_mean_mm[np.isfinite(self.lopo_pose_mean_mm)]
        return float(v.max()) if v.size else float("nan")

    def to_dict(self) -> dict[str, Any]:
        """The ``calibration.json`` body (without provenance, which the caller adds)."""
        return {
            "tool0_from_phantom": self.tool0_from_phantom.tolist(),
            "image_from_robot": self.image_from_robot.tolist(),
            "parameters": [
                {"name": p.name, "value": float(v), "std_error": float(s), "unit": p.unit}
                for p, v, s in zip(self.parameters, self.values, self.std_errors, strict=True)
            ],
            "dropped_parameters": list(self.dropped),
            "identification": {
                "rank": self.rank,
                "n_parameters": len(self.parameters),
                "condition_number": _finite_or_none(self.condition_number),
                "singular_values": self.singular_values.tolist(),
            },
            "fit_rms_mm": self.fit_rms_mm,
            "poses": [
                {
                    "name": n,
                    "used": bool(u),
                    "rms_mm": float(r),
                    "max_mm": float(m),
                    "sphere_indices": [int(i) for i in k],
                    "sphere_residuals_mm": s.tolist(),
                    "leave_one_out_mean_mm": None if not math.isfinite(lo) else float(lo),
                    "leave_one_out_rms_mm": None if not math.isfinite(lr) else float(lr),
                }
                for n, u, r, m, k, s, lo, lr in zip(
                    self.pose_names,
                    self.used,
                    self.pose_rms_mm,
                    self.pose_max_mm,
                    self.sphere_indices,
                    self.sphere_residuals_mm,
                    self.lopo_pose_mean_mm,
                    self.lopo_pose_rms_mm,
                    strict=True,
                )
            ],
            "outlier_poses": list(self.outliers),
            "leave_one_pose_out_mean_mm": _finite_or_none(self.lopo_mean_mm),
            "leave_one_pose_out_max_mm": _finite_or_none(self.lopo_max_mm),
            "leave_one_pose_out_tre_rms_mm": _finite_or_none(self.lopo_tre_rms_mm),
            "fle_rms_mm": self.fle_rms_mm,
            "registration_tre_rms_mm": self.registration_tre_rms_mm,
            "predicted_held_out_rms_mm": _finite_or_none(self.predicted_held_out_rms_mm),
            "lopo_predicted_rms_mm": _finite_or_none(self.lopo_predicted_rms_mm),
            "predicted_chain_error_mm": _finite_or_none(self.predicted_chain_error_mm),
            "target_rms_mm": self.target_rms_mm,
            "target_met": bool(self.predicted_held_out_rms_mm <= self.target_rms_mm),
            "estimator": self.estimator,
            "prior_scale": _finite_or_none(self.prior_scale),
            "cross_validation": (
                None
                if self.cv_scores is None
                else [{"prior_scale": k, "mean_sq_mm2": v} for k, v in self.cv_scores.items()]
            ),
            "unmodelled_rms_mm": _finite_or_none(self.unmodelled_rms_mm),
            "unmodelled": None if self.unmodelled is None else self.unmodelled.to_dict(),
            "working_volume": self.working_volume,
            "predicted_working": (
                None
                if self.prediction is None
                else {
                    "rms_mm": self.prediction.rms_mm,
                    "max_mm": self.prediction.max_mm,
                    "n_poses": len(self.prediction.per_pose_rms_mm),
                    "weak_direction": [
                        {"parameter": n, "share": v} for n, v in self.prediction.weak_direction
                    ],
                }
            ),
            "timings_s": dict(self.timings_s),
            "software": f"oarmreg {__version__}",
        }


def _finite_or_none(v: float) -> float | None:
    """JSON has no NaN / inf: report a figure that was not computed as null."""
    return float(v) if math.isfinite(v) else None


@dataclass(frozen=True)
class UnmodelledEstimate:
    """The per-pose error no geometric model has (mm, 3-D RMS), as the prediction uses it, and
    where it came from (``CalibrationParams.unmodelled_source``; docs/calibration.md)."""

    rms_mm: float
    """What the prediction used (at least ``CalibrationParams.repeatability_rms_mm``)."""
    source: Literal["leave-one-pose-out", "leave-one-pose-out, widened to the prior", "prior"]
    """``"leave-one-pose-out"``: the session's own held-out residuals (upper bound
    û² + f·se); ``"… widened to the prior"``: they could not pin it better than the prior
    (one standard error wider than ``unmodelled_floor_mm``), so at least the prior;
    ``"prior"``: ``unmodelled_floor_mm`` (too few poses, or asked for)."""
    reason: str
    """One sentence for the record: the figures behind ``source``."""
    loo_mm2: float = float("nan")
    """û² (mm², may be < 0: noise) of :func:`registration.calibration.prediction.loo_unmodelled`."""
    loo_se_mm2: float = float("nan")
    """Its standard error (mm²)."""
    n_poses: int = 0
    """Poses with a held-out residual behind the estimate."""
    in_sample_rms_mm: float = float("nan")
    """The rigid residual the fit leaves at its own poses (biased low: the fit absorbs most of it)."""

    @property
    def loo_rms_mm(self) -> float:
        """√max(û², 0): the held-out estimate itself, before the standard error is added."""
        return math.sqrt(max(self.loo_mm2, 0.0)) if math.isfinite(self.loo_mm2) else float("nan")

    def to_dict(self) -> dict[str, Any]:
        return {
            "rms_mm": self.rms_mm,
            "source": self.source,
            "reason": self.reason,
            "leave_one_pose_out_rms_mm": _finite_or_none(self.loo_rms_mm),
            "leave_one_pose_out_mm2": _finite_or_none(self.loo_mm2),
            "leave_one_pose_out_se_mm2": _finite_or_none(self.loo_se_mm2),
            "n_poses": self.n_poses,
            "in_sample_rms_mm": _finite_or_none(self.in_sample_rms_mm),
        }


@dataclass(frozen=True, eq=False)
class WorkingPrediction:
    """The predicted error over the working volume (mm) and what limits it."""

    joints_rad: F64
    """(W, n) sampled poses of the working volume."""
    registration_joints_rad: F64
    per_pose_rms_mm: F64
    """RMS sphere error predicted at each sampled pose (chain posterior + unmodelled + registration)."""
    chain_rms_mm: F64
    """... its part from the calibrated model's posterior alone."""
    registration_rms_mm: F64
    """... its part from the one-scan registration's detection error (TRE at the pose's spheres)."""
    rms_mm: float
    max_mm: float
    weak_direction: tuple[tuple[str, float], ...]
    """Parameters of the direction that dominates the worst pose's error, with their share."""
    exciting_joints_rad: F64
    """(≤ 3, n) poses inside the scan volume whose spheres move most along that direction."""


def chain_error_figure(calibration: Mapping[str, Any] | None) -> tuple[float, str]:
    """(predicted_chain_error_mm, its source) of a registration made with ``calibration``: the
    active calibration's posterior figure, else the nominal model's prior."""
    if calibration is not None:
        v = calibration.get("predicted_chain_error_mm")
        if v is not None:
            return float(v), f"calibration {calibration.get('calibration_id')} posterior"
        return NOMINAL_CHAIN_ERROR_MM, (
            f"calibration {calibration.get('calibration_id')} has no posterior figure "
            "(made before chain figures existed): nominal prior"
        )
    return NOMINAL_CHAIN_ERROR_MM, "nominal model prior (no active calibration)"
