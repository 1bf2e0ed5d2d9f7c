"""Multi-pose calibration of robot geometry, connecting rod and O-arm placement (issue #10).

One session = K ≥ 6 scans of the phantom at different robot poses with the
O-arm left in place (one FrameOfReferenceUID).  Sphere ``k`` detected in scan
``i`` at ``d_ik`` (image, mm) is explained by::

    d_ik = Y · T(q_i; θ) · X · p_k

``Y`` = ``image_from_robot`` of the session, ``X`` = ``tool0_from_phantom``,
``T`` the arm's forward kinematics (:class:`~registration.urdf_writer.SerialChain`)
with joint-origin corrections ``θ``, ``p_k`` the phantom's CAD centres.

**Parameter set** (``CalibrationParams.parameter_set``).  Each joint origin
``M_i`` gets a small correction ``M_i · E(ω, v)`` (rotation vector ω, translation
v, in joint *i*'s frame); a rotation about the joint's own axis ``a_i`` is its
zero offset.  Not all 36 components are identifiable: a rotation about / a
translation along ``a_i`` commutes with ``Rot(a_i, q_i)`` and so moves into the
next origin (or into X after the last joint), everything before joint 1 (and
joint 1's offset) is absorbed by Y, and everything after joint 6 by X.  With
the 12 parameters of X and Y this leaves the 30 of the minimal complete model
of a 6R arm measured in full pose (4R + 2P + 6, research/calibration.md §1),
i.e. **18 robot parameters**.  :func:`parameter_candidates` lists the 36 in a
fixed priority (offsets first, then axis tilts, axis shifts, slides) and
:func:`minimal_parameter_set` keeps, in that order, every one that adds rank
to the identification Jacobian at generic configurations — FIGAROH's QR
selection (research note §1), done greedily so the kept set is readable.
For the TX60 (and TX2-60) it is, 18 in all: the zero offsets of J2–J5 (4);
origin tilts J2 x, J3 x and z, J4 x, J5 x, J6 x and y (7); origin shifts J2 x,
J3 z, J4 x and y, J5 x and z, J6 y (7).  (Frames of the URDF: J1, J4, J6 turn
about z, J2, J3, J5 about y.)  J1's origin and offset and J6's offset are
absorbed by Y and X; parallel J2/J3 cost the shift of J3 along x.  Plain DH
would be singular for that parallel pair (research note §1); these local
origin corrections are not.
``"offsets"`` fits X, Y and the joint offsets only (research note §1,
"joint-offset-only model"); ``"hand-eye"`` fits X and Y only.

**Method.** Shah's closed form for AX = YB (Kronecker product, doi:10.1115/1.4024473)
from per-pose rigid fits gives X and Y with nominal kinematics; then
``scipy.optimize.least_squares`` (TRF, analytic Jacobian, ``x_scale="jac"``) on all sphere
residuals with a robust soft-L1 loss estimates X, Y and θ jointly (research note §2: point LSQ
after Shah).  The loss is applied to each sphere's 3-D distance (a callable loss, see
:func:`_sphere_soft_l1`), not to its x, y, z separately, so it does not depend on the image axes.

**Identifiability.** The SVD of the column-normalised Jacobian gives numeric
rank and condition number; above ``max_condition`` (default 100, Schroer et
al. as quoted by Nahvi & Hollerbach, ICRA 1996, research note §1) the set is
refused naming the parameters of the weakest direction and the motion to add,
or (``on_weak="drop"``) those robot parameters are dropped until it passes.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Final, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from registration import __version__
from registration.errors import OarmRegError, RegistrationError
from registration.frames import as_transform, invert, make_transform
from registration.rigid import fit_rigid, nearest_rotation
from registration.urdf_writer import SerialChain, rotation_about

if TYPE_CHECKING:
    from registration.pose_sampling import ScanVolume

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

NOMINAL_CHAIN_ERROR_MM: Final = 1.0
"""``predicted_chain_error_mm`` of a registration made with the nominal model and rod (no active
calibration): issue #20 measured 1.03 mm mean held-out error of the nominal model on a TX60 cell it
was not tuned on; the test bed's nominal model gives 1.0–1.4 mm at error scale 1
(``python -m benchmarks.bench_calibration``)."""
DROP_CONDITION: Final = 100.0
"""``--drop-weak`` drops until the condition number is ≤ this when no ``max_condition`` is given
(Schroer et al. via Nahvi & Hollerbach 1996, research/calibration.md §1)."""
MIN_POSES: Final = 6
"""Issue #10: K ≥ 6 scans per session."""
FD_STEP: Final = 1e-6
"""Central-difference step of the Jacobian (rad or mm): truncation ~1e-12, round-off ~1e-10."""
MAX_NFEV: Final = 100
"""Residual evaluations of the robust fit at most (the 10 × 28 benchmark session takes ~15)."""
FTOL: Final = 1e-12
"""``least_squares`` ftol: relative cost decrease to stop at.  On the 10 × 28 session of
``benchmarks/bench_calibration.py --solve-only`` it stops after ~15 evaluations instead of ~33 at
machine epsilon, the parameters within 3e-8 (rad, mm) of the ε-converged ones (the smallest
standard error is 1e-5); on exact data the cost falls by more than this every step until round-off, so
held-out poses are still recovered to 1e-6 mm (tests/unit/test_calibration.py)."""
XTOL: Final = float(np.finfo(np.float64).eps)
"""``least_squares`` xtol and gtol: machine epsilon, the smallest scipy accepts (a backstop; the
hand-written LM ``least_squares`` replaced stopped on a 1e-13 scaled step)."""
GTOL: Final = XTOL
TR_SOLVER: Final = "lsmr"
"""Trust-region subproblem solver of TRF: ``"lsmr"`` (matrix-vector products only), not
``"exact"``, whose SVD of the (3L, P) Jacobian per iteration goes through scipy's threaded OpenBLAS
— on the shared 2-core machine 0.09–0.47 s per 840 × 30 SVD vs 4 ms single-threaded (measured
with ``OPENBLAS_NUM_THREADS=1``; threadpoolctl is not installed): 0.5–2.2 s per calibration
without LOPO vs 0.2–0.6 s with lsmr (``benchmarks/bench_calibration.py --solve-only``)."""
LSMR_TOL: Final = 1e-14
"""lsmr ``atol`` = ``btol`` of the TRF subproblem.  At lsmr's default 1e-6 the inexact steps stall
TRF (100 evaluations, not converged, measured); at 1e-14 it converges as with ``"exact"``."""
MIN_JOINT_SPREAD_DEG: Final = 5.0
"""A joint whose range over the session's poses is below this is named as not moving."""
STRUCTURAL_RANK_TOL: Final = 1e-5
"""A candidate column whose normalised residual after projection on the kept ones is below this is
structurally redundant (exact redundancies leave ~1e-10, genuine parameters ≥ 1e-2)."""


@dataclass(frozen=True)
class Priors:
    """Gaussian prior widths (σ per component) of the robot's geometric errors (issue #20).

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
    the issue #20 cell's rod was off 0.8 mm / 0.4° in all; 1 mm / 0.5° per axis covers it."""
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


class CalibrationError(RegistrationError):
    """A calibration was refused.  Subclasses say why."""

    title = "Calibration refused"


class TooFewPosesError(CalibrationError):
    title = "Too few calibration poses"


class SessionMismatchError(CalibrationError):
    title = "Scans from different O-arm placements"


class NotIdentifiableError(CalibrationError):
    title = "Calibration parameters not identifiable from these poses"


class OutlierPoseError(CalibrationError):
    title = "Calibration pose inconsistent with the others"


@dataclass(frozen=True)
class CalibrationParams:
    """Settings of :func:`calibrate` (lengths in mm)."""

    parameter_set: Literal["full", "offsets", "hand-eye", "all"] = "full"
    estimator: Literal["map", "ls"] = "ls"
    """``"ls"``: robust least squares over the minimal complete set, no prior; ``"map"``: maximum a
    posteriori with Gaussian priors (:data:`PRIORS`) on all 6 error components of every joint
    origin (``parameter_set="full"`` becomes ``"all"``), their weight chosen by cross-validation
    over poses.  Default ``"ls"``: on the issue #20 test bed (tuning seeds 1–3 × error scales 1, 2
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
    issue #10 DICOM session; the cross-validated scale s absorbs any mismatch."""
    working_margin_mm: float = 40.0
    """Working volume = the scan volume grown by this (radius and half-length, mm): navigation
    uses the arm beyond the phantom's calibration positions — the phantom is 60 mm across and a
    target 150 mm from it (the registration's TRE targets) sits up to ~40 mm outside the volume
    when the phantom is at its edge.  The prediction and the refusal are over this volume."""
    unmodelled_floor_mm: float = 0.04
    """Least RMS per-pose error (mm, 3-D) no geometric model has — compliance/sag, backlash,
    repeatability — used when the residuals show less (a fit absorbs most of it at its own poses).
    Origin: Stäubli TX60 repeatability ± 0.02 mm [unverified datasheet value] and non-geometric
    errors ≈ 10 % of the position error (Klimchik et al., research/calibration.md §1) of the
    TX60's 0.31 mm nominal error: √(0.02² + 0.031²) ≈ 0.04 mm."""
    farthest_split: bool = False
    """Scale the posterior by how optimistic it was on the poses farthest from the rest (≥ 1).
    Off by default: with 10 poses the ⌈K/4⌉ held-out poses make a noisy factor (1–15 on the
    tuning seeds), which pushed predicted / measured above 1.5 on 4 of 12 sets, against 1 without."""
    max_predicted_error_mm: float = 0.5
    """Refuse when the predicted RMS sphere error at the worst pose of the working volume exceeds
    this (mm).  0.5 mm: research/calibration.md §6 suggested gate on predicted TRE, half the
    ≈ 1 mm the nominal model gives (issue #20)."""
    min_poses: int = MIN_POSES
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
    prediction: WorkingPrediction | None = None
    working_volume: dict[str, Any] | None = None

    @property
    def predicted_held_out_rms_mm(self) -> float:
        """Expected RMS sphere-centre error at a pose of the working volume after a one-scan
        registration with the calibrated model: the posterior propagated through the kinematics
        (issue #20); without a prediction the LOPO figure :attr:`lopo_predicted_rms_mm`."""
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
        """Issue #10's figure: √(LOPO TRE² + registration TRE²) — only sees poses like the others."""
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
            "estimator": self.estimator,
            "prior_scale": _finite_or_none(self.prior_scale),
            "cross_validation": (
                None
                if self.cv_scores is None
                else [{"prior_scale": k, "mean_sq_mm2": v} for k, v in self.cv_scores.items()]
            ),
            "unmodelled_rms_mm": _finite_or_none(self.unmodelled_rms_mm),
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


# ---------------------------------------------------------------- parametrisation


def _perpendicular_pair(axis: F64) -> tuple[F64, F64]:
    """Two unit vectors ⟂ ``axis`` (the other coordinate axes when ``axis`` is one)."""
    e = np.eye(3)
    k = int(np.argmax(np.abs(axis)))
    if abs(abs(axis[k]) - 1.0) < 1e-12:
        others = [e[j] for j in range(3) if j != k]
        return others[0], others[1]
    u = np.cross(axis, e[int(np.argmin(np.abs(axis)))])
    u /= np.linalg.norm(u)
    return u, np.cross(axis, u)


def _dir_name(d: F64) -> str:
    for j, n in enumerate("xyz"):
        if abs(abs(d[j]) - 1.0) < 1e-12:
            return ("-" if d[j] < 0 else "") + n
    return "(" + ",".join(f"{v:+.3f}" for v in d) + ")"


def parameter_candidates(chain: SerialChain) -> list[Parameter]:
    """Every candidate, in selection priority: Y (6), X (6), offsets, tilts, shifts, slides."""
    e = np.eye(3)
    out = [
        Parameter(f"{g} {k} {n}", g, k, tuple(e[j]))
        for g in ("image_from_robot", "tool0_from_phantom")
        for k in ("rot", "trans")
        for j, n in enumerate("xyz")
    ]
    names, axes = chain.joint_names, chain.axes
    out += [Parameter(f"{names[i]} offset", names[i], "rot", tuple(axes[i])) for i in range(len(names))]
    for i, name in enumerate(names):
        u, w = _perpendicular_pair(axes[i])
        out += [Parameter(f"{name} origin tilt {_dir_name(d)}", name, "rot", tuple(d)) for d in (u, w)]
    for i, name in enumerate(names):
        u, w = _perpendicular_pair(axes[i])
        out += [Parameter(f"{name} origin shift {_dir_name(d)}", name, "trans", tuple(d)) for d in (u, w)]
    out += [
        Parameter(f"{n} origin slide {_dir_name(axes[i])}", n, "trans", tuple(axes[i]))
        for i, n in enumerate(names)
    ]
    return out


def _rotvec_matrix(w: F64) -> F64:
    ang = float(np.linalg.norm(w))
    if ang == 0.0:
        return np.eye(3)
    k = w / ang
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.asarray(np.eye(3) + math.sin(ang) * kx + (1.0 - math.cos(ang)) * (kx @ kx), dtype=np.float64)


def _corrections(params: Sequence[Parameter], values: F64) -> dict[str, F64]:
    """group → E(ω, v) (4 × 4) from the parameter values."""
    acc: dict[str, tuple[F64, F64]] = {}
    for p, v in zip(params, values, strict=True):
        w, t = acc.setdefault(p.group, (np.zeros(3), np.zeros(3)))
        (w if p.kind == "rot" else t)[:] += float(v) * np.asarray(p.direction)
    return {g: make_transform(_rotvec_matrix(w), t) for g, (w, t) in acc.items()}


@dataclass(frozen=True, eq=False)
class _Model:
    """Nominal X, Y, chain and the parameter list: maps a parameter vector to (Y, X, chain)."""

    y0: F64
    x0: F64
    chain: SerialChain
    params: tuple[Parameter, ...]
    prior_weights: F64 | None = None
    """Per parameter σ_d / (s σ_j) of the MAP prior residual (0 = flat prior); None = plain LS."""

    def with_prior(self, weights: F64 | None) -> _Model:
        return _Model(self.y0, self.x0, self.chain, self.params, weights)

    def unpack(self, values: F64) -> tuple[F64, F64, SerialChain]:
        c = _corrections(self.params, values)
        eye = np.eye(4)
        y = self.y0 @ c.get("image_from_robot", eye)
        x = self.x0 @ c.get("tool0_from_phantom", eye)
        m = np.stack(
            [
                mi @ c.get(n, eye)
                for mi, n in zip(self.chain.parent_from_joint, self.chain.joint_names, strict=True)
            ]
        )
        return y, x, self.chain.with_origins(m)

    def predict(self, values: F64, joints_rad: F64, pts_phantom_mm: F64, pose_of: I64) -> F64:
        y, x, chain = self.unpack(values)
        t = y @ chain.robot_from_tool0_batch(joints_rad) @ x
        tp = t[pose_of]
        return np.asarray(
            np.einsum("lij,lj->li", tp[:, :3, :3], pts_phantom_mm) + tp[:, :3, 3], dtype=np.float64
        )


@dataclass(frozen=True, eq=False)
class _Data:
    joints_rad: F64  # (K, n)
    pts_phantom_mm: F64  # (L, 3)
    meas_image_mm: F64  # (L, 3)
    pose_of: I64  # (L,)

    def subset(self, keep: NDArray[np.bool_]) -> _Data:
        new_index = np.cumsum(keep) - 1
        rows = keep[self.pose_of]
        return _Data(
            self.joints_rad[keep],
            self.pts_phantom_mm[rows],
            self.meas_image_mm[rows],
            new_index[self.pose_of[rows]].astype(np.int64),
        )


def _residuals(model: _Model, data: _Data, values: F64) -> F64:
    pred = model.predict(values, data.joints_rad, data.pts_phantom_mm, data.pose_of)
    return np.asarray((pred - data.meas_image_mm).reshape(-1), dtype=np.float64)


def _jacobian_fd(model: _Model, data: _Data, values: F64) -> F64:
    """Central-difference Jacobian (3L, P) of the residuals (the reference for the analytic one)."""
    cols = []
    for j in range(len(values)):
        step = np.zeros_like(values)
        step[j] = FD_STEP
        cols.append(
            (_residuals(model, data, values + step) - _residuals(model, data, values - step)) / (2 * FD_STEP)
        )
    return np.stack(cols, axis=1)


def _frames(model: _Model, values: F64, joints_rad: F64) -> tuple[F64, dict[str, tuple[F64, F64]]]:
    """``image_from_phantom`` (K, 4, 4) and, per group, (R_A (K, 3, 3), o_F (K, 3)).

    ``A`` is everything left of the group's correction ``E``; ``F = A · E``.  A rotation
    parameter about ``d`` moves a point P by (R_A d) × (P − o_F) per radian, a translation
    parameter by R_A d per mm (exact at zero corrections, first-order in them otherwise).
    """
    c = _corrections(model.params, values)
    eye = np.eye(4)
    k = len(joints_rad)
    out: dict[str, tuple[F64, F64]] = {}
    cur = np.broadcast_to(model.y0, (k, 4, 4)).copy()
    e = c.get("image_from_robot", eye)
    out["image_from_robot"] = (cur[:, :3, :3].copy(), (cur @ e)[:, :3, 3].copy())
    cur = cur @ e
    ch = model.chain
    for i, name in enumerate(ch.joint_names):
        cur = cur @ ch.parent_from_joint[i]
        e = c.get(name, eye)
        out[name] = (cur[:, :3, :3].copy(), (cur @ e)[:, :3, 3].copy())
        cur = cur @ e
        cur[:, :3, :3] = cur[:, :3, :3] @ rotation_about(ch.axes[i], joints_rad[:, i])
    cur = cur @ ch.last_from_tool0 @ model.x0
    e = c.get("tool0_from_phantom", eye)
    out["tool0_from_phantom"] = (cur[:, :3, :3].copy(), (cur @ e)[:, :3, 3].copy())
    return cur @ e, out


def _jacobian(model: _Model, data: _Data, values: F64) -> F64:
    """Analytic Jacobian (3L, P) of the residuals (see :func:`_frames`)."""
    t, frames = _frames(model, values, data.joints_rad)
    tp = t[data.pose_of]
    world = np.einsum("lij,lj->li", tp[:, :3, :3], data.pts_phantom_mm) + tp[:, :3, 3]
    groups = [p.group for p in model.params]
    rot_a = np.stack([frames[g][0] for g in groups])  # (P, K, 3, 3)
    o_f = np.stack([frames[g][1] for g in groups])[:, data.pose_of]  # (P, L, 3)
    dirs = np.array([p.direction for p in model.params], dtype=np.float64)
    axis = np.einsum("pkij,pj->pki", rot_a, dirs)[:, data.pose_of]  # (P, L, 3)
    is_rot = np.array([p.kind == "rot" for p in model.params])
    cols = np.where(is_rot[:, None, None], np.cross(axis, world[None] - o_f), axis)
    return np.asarray(cols.reshape(len(groups), -1).T, dtype=np.float64)


def _normalised_svd(jac: F64) -> tuple[F64, F64]:
    """Singular values (descending) and right singular vectors (rows) of the column-normalised
    Jacobian, from the eigen-decomposition of its P × P normal matrix (no tall-matrix LAPACK)."""
    norms = np.sqrt(np.einsum("ij,ij->j", jac, jac))
    norms[norms == 0.0] = 1.0
    jn = jac / norms
    lam, vec = np.linalg.eigh(np.einsum("ij,ik->jk", jn, jn))
    order = np.argsort(lam)[::-1]
    return np.sqrt(np.clip(lam[order], 0.0, None)), np.asarray(vec[:, order].T, dtype=np.float64)


def minimal_parameter_set(chain: SerialChain, parameter_set: str = "full") -> tuple[Parameter, ...]:
    """The identifiable subset of :func:`parameter_candidates` (see the module docstring).

    Structural: evaluated at 24 fixed generic configurations inside the joint
    limits with 4 non-coplanar points, so the result depends on the arm only.
    """
    cands = parameter_candidates(chain)
    if parameter_set == "hand-eye":
        return tuple(cands[:12])
    if parameter_set == "all":  # every joint origin in 6 DoF: only meaningful with priors (MAP)
        return tuple(cands)
    gen = np.random.default_rng(20181016)  # fixed: a structural property, not a sample
    lo, hi = np.maximum(chain.lower_rad, -2.0), np.minimum(chain.upper_rad, 2.0)
    q = lo + (hi - lo) * gen.uniform(0.1, 0.9, (24, chain.n_joints))
    pts = np.array([[40.0, 0, 0], [0, 40.0, 0], [0, 0, 40.0], [-30.0, -30.0, -30.0]])
    data = _Data(q, np.tile(pts, (24, 1)), np.zeros((96, 3)), np.repeat(np.arange(24), 4))
    model = _Model(np.eye(4), np.eye(4), chain, tuple(cands))
    jac = _jacobian(model, data, np.zeros(len(cands)))
    jac = jac / np.linalg.norm(jac, axis=0).clip(1e-300)
    basis = np.zeros((jac.shape[0], 0))
    kept: list[Parameter] = []
    for j, p in enumerate(cands):
        if parameter_set == "offsets" and j >= 12 and not p.name.endswith(" offset"):
            continue
        r = jac[:, j] - basis @ (basis.T @ jac[:, j])
        if np.linalg.norm(r) > STRUCTURAL_RANK_TOL:
            basis = np.column_stack([basis, r / np.linalg.norm(r)])
            kept.append(p)
    return tuple(kept)


# ---------------------------------------------------------------- closed-form start


def shah_ax_yb(a: Sequence[F64], b: Sequence[F64]) -> tuple[F64, F64]:
    """Solve A_i X = Y B_i for rigid X, Y (Shah 2013, doi:10.1115/1.4024473), numpy only.

    Rotation: (I ⊗ R_A) vec R_X − (R_Bᵀ ⊗ I) vec R_Y = 0 (column-major vec) stacked over the
    poses; the null vector is scaled to det +1 and projected onto SO(3).  Translation: linear
    least squares of R_A t_X − t_Y = R_Y t_B − t_A.

    Returns
    -------
    x, y : ndarray, shape (4, 4)
    """
    eye = np.eye(3)
    rows = [
        np.hstack([np.kron(eye, ai[:3, :3]), -np.kron(bi[:3, :3].T, eye)])
        for ai, bi in zip(a, b, strict=True)
    ]
    _, _, vt = np.linalg.svd(np.vstack(rows))
    v = vt[-1]
    vx, vy = v[:9].reshape(3, 3, order="F"), v[9:].reshape(3, 3, order="F")
    det_x = float(np.linalg.det(vx))
    scale = math.copysign(abs(det_x) ** (-1.0 / 3.0), det_x) if det_x != 0.0 else 1.0
    rx, _ = nearest_rotation(scale * vx)
    ry, _ = nearest_rotation(scale * vy)
    lhs = np.vstack([np.hstack([ai[:3, :3], -eye]) for ai in a])
    rhs = np.concatenate([ry @ bi[:3, 3] - ai[:3, 3] for ai, bi in zip(a, b, strict=True)])
    t, *_ = np.linalg.lstsq(lhs, rhs, rcond=None)
    return make_transform(rx, t[:3]), make_transform(ry, t[3:])


def _initial_estimate(
    poses: Sequence[MatchedPose], chain: SerialChain, centres_phantom_mm: F64
) -> tuple[F64, F64]:
    """(image_from_robot, tool0_from_phantom) from per-pose rigid fits and Shah with nominal FK."""
    robot_from_tool0 = chain.robot_from_tool0_batch(np.stack([p.joints_rad for p in poses]))
    image_from_phantom = [fit_rigid(centres_phantom_mm[p.sphere_indices], p.centres_image_mm) for p in poses]
    # Y B X = A  ⇔  B X = Y⁻¹ A: Shah's A X = Y B with A = robot_from_tool0, B = image_from_phantom
    x, robot_from_image = shah_ax_yb(list(robot_from_tool0), image_from_phantom)
    return invert(robot_from_image), x


# ---------------------------------------------------------------- checks and advice


def check_session(poses: Sequence[MatchedPose], min_poses: int = MIN_POSES) -> None:
    """Refuse fewer than ``min_poses`` scans or scans from several O-arm placements.

    Raises
    ------
    TooFewPosesError, SessionMismatchError
    """
    if len(poses) < min_poses:
        raise TooFewPosesError(
            f"calibration needs at least {min_poses} scans at different poses, got {len(poses)}; "
            "add scans that tilt the phantom by ±45° about two axes and turn the wrist"
        )
    groups: dict[str, list[str]] = {}
    for p in poses:
        groups.setdefault(p.frame_of_reference_uid, []).append(p.name)
    if len(groups) > 1:
        listing = "; ".join(f"FrameOfReferenceUID {u or '(none)'}: {', '.join(n)}" for u, n in groups.items())
        raise SessionMismatchError(
            "all scans of a calibration session must share one O-arm placement (one "
            f"FrameOfReferenceUID (0020,0052)); found {len(groups)}: {listing}. Rescan the odd ones "
            "without moving the O-arm, or run one calibration per placement"
        )


def _motion_advice(weak: Sequence[Parameter], joints_rad: F64, names: Sequence[str]) -> str:
    """Which motion to add: the joints that barely move, else the joints of the weakest direction."""
    spread_deg = np.degrees(np.ptp(joints_rad, axis=0))
    still = [n for n, s in zip(names, spread_deg, strict=True) if s < MIN_JOINT_SPREAD_DEG]
    moving = [n for n in names if n not in still]
    parts = []
    if still:
        if moving and len(moving) <= 2:
            parts.append(f"the poses differ only in {', '.join(moving)}")
        ranges = ", ".join(f"{n} ({s:.1f}°)" for n, s in zip(names, spread_deg, strict=True) if n in still)
        parts.append(f"joints that barely move across the poses: {ranges}")
        parts.append(f"add poses that move {', '.join(still)} by ±45° or more")
    weak_joints = sorted({p.group for p in weak if p.group in names} - set(still))
    if any(p.group in ("image_from_robot", "tool0_from_phantom") for p in weak) and not still:
        parts.append(
            "add poses that rotate the phantom about at least two non-parallel axes by ±45° and "
            "shift it within the scan volume"
        )
    if weak_joints:
        parts.append(f"add poses that move {', '.join(weak_joints)} (and its neighbours) over a wider range")
    return "; ".join(parts)


def _identifiability(
    jac: F64, params: Sequence[Parameter], rtol: float
) -> tuple[int, float, F64, list[Parameter], list[Parameter]]:
    """(rank, condition number, singular values, main parameters of the weakest direction, all
    parameters by decreasing weight in it)."""
    s, vt = _normalised_svd(jac)
    rank = int(np.sum(s > rtol * s[0]))
    cond = float(s[0] / s[-1]) if s[-1] > 0 else float("inf")
    v = np.abs(vt[-1])
    order = np.argsort(-v)
    weak = [params[j] for j in order if v[j] >= 0.5 * v.max()]
    return rank, cond, s, weak, [params[j] for j in order]


def _select_parameters(
    model: _Model, data: _Data, params: CalibrationParams, names: Sequence[str]
) -> tuple[_Model, tuple[str, ...], int, float, F64]:
    """Check identifiability at the start; refuse or drop weak robot parameters."""
    dropped: list[str] = []
    limit = params.max_condition
    if limit is None and params.on_weak == "drop":
        limit = DROP_CONDITION
    while True:
        jac = _jacobian(model, data, np.zeros(len(model.params)))
        rank, cond, s, weak, ranked = _identifiability(jac, model.params, params.rank_rtol)
        if limit is None or cond <= limit:
            return model, tuple(dropped), rank, cond, s
        robot_weak = [p for p in ranked if p.group in names]
        if params.on_weak == "drop" and robot_weak:
            dropped.append(robot_weak[0].name)
            model = _Model(
                model.y0, model.x0, model.chain, tuple(p for p in model.params if p is not robot_weak[0])
            )
            continue
        raise NotIdentifiableError(
            f"the {len(data.joints_rad)} poses do not identify the requested '{params.parameter_set}' "
            f"set of {len(model.params)} parameters: numeric rank {rank}, condition number {cond:.3g} > "
            f"{limit:g} (--max-condition); weakest: {', '.join(p.name for p in weak[:4])}. "
            f"{_motion_advice(weak, data.joints_rad, names)}"
        )


# ---------------------------------------------------------------- fitting


def _sphere_soft_l1(z: F64) -> F64:
    """soft-L1 ρ(s) = 2(√(1+s) − 1) of each sphere's squared 3-D distance s = Σ over its x, y, z
    components of ``z`` (already divided by ``f_scale``²), in ``least_squares``'s callable-loss form:
    rows ρ, ρ′, ρ″ per residual component (ρ split in three so the cost sums per sphere).

    ρ″ is returned as 0: the cross-component Hessian of a per-sphere loss is not diagonal, and
    with 0 the trust-region model is the IRLS one (gradient exact, weights ρ′ per sphere)."""
    s = np.repeat(z.reshape(-1, 3).sum(axis=1), 3)
    root = np.sqrt(1.0 + s)
    return np.stack([2.0 * (root - 1.0) / 3.0, 1.0 / root, np.zeros_like(s)])


def _prior_loss(n_data: int) -> Any:
    """The per-sphere soft-L1 on the first ``n_data`` components, a plain square on the prior rows."""

    def loss(z: F64) -> F64:
        out = np.empty((3, len(z)))
        out[:, :n_data] = _sphere_soft_l1(z[:n_data])
        out[0, n_data:], out[1, n_data:], out[2, n_data:] = z[n_data:], 1.0, 0.0
        return out

    return loss


def _augmented(model: _Model, data: _Data) -> tuple[Any, Any, Any]:
    """(residuals, Jacobian, loss) of the MAP cost: sphere residuals, then w_j θ_j per prior row."""
    w = model.prior_weights
    if w is None or not np.any(w > 0):
        return (lambda v: _residuals(model, data, v)), (lambda v: _jacobian(model, data, v)), _sphere_soft_l1
    rows = np.flatnonzero(w > 0)
    prior_jac = np.zeros((len(rows), len(w)))
    prior_jac[np.arange(len(rows)), rows] = w[rows]
    n_data = 3 * len(data.pose_of)

    def fun(v: F64) -> F64:
        return np.concatenate([_residuals(model, data, v), w[rows] * v[rows]])

    def jac(v: F64) -> F64:
        return np.vstack([_jacobian(model, data, v), prior_jac])

    return fun, jac, _prior_loss(n_data)


def _fit(model: _Model, data: _Data, x0: F64, params: CalibrationParams) -> F64:
    """Robust least squares on all sphere residuals: ``scipy.optimize.least_squares`` (TRF) with
    the analytic Jacobian and a soft-L1 loss of scale ``robust_scale_mm`` on each sphere's 3-D
    distance (issue #10); with ``model.prior_weights`` the MAP cost (prior rows squared, issue #20)."""
    fun, jac, loss = _augmented(model, data)
    res = least_squares(
        fun,
        np.asarray(x0, dtype=np.float64),
        jac=jac,
        method="trf",
        loss=loss,
        f_scale=params.robust_scale_mm,
        x_scale="jac",
        tr_solver=TR_SOLVER,
        tr_options={"atol": LSMR_TOL, "btol": LSMR_TOL} if TR_SOLVER == "lsmr" else {},
        ftol=FTOL,
        xtol=XTOL,
        gtol=GTOL,
        max_nfev=MAX_NFEV,
    )
    return np.asarray(res.x, dtype=np.float64)


def _per_pose(model: _Model, data: _Data, values: F64, n_poses: int) -> tuple[F64, F64, list[F64]]:
    err = np.linalg.norm(_residuals(model, data, values).reshape(-1, 3), axis=1)
    per = [err[data.pose_of == i] for i in range(n_poses)]
    rms = np.array([math.sqrt(float(np.mean(e**2))) if e.size else float("nan") for e in per])
    mx = np.array([float(e.max()) if e.size else float("nan") for e in per])
    return rms, mx, per


def _outliers(rms_mm: F64, used: NDArray[np.bool_], params: CalibrationParams) -> NDArray[np.bool_]:
    med = float(np.median(rms_mm[used]))
    return np.asarray(
        used & (rms_mm > max(params.outlier_factor * med, params.outlier_floor_mm)), dtype=np.bool_
    )


def _leave_one_out(
    model: _Model, data: _Data, values: F64, used: NDArray[np.bool_], params: CalibrationParams
) -> tuple[F64, F64]:
    """Mean and RMS sphere prediction error (mm) of each used pose from a fit without it (NaN if unused)."""
    out = np.full(len(used), np.nan)
    out_rms = np.full(len(used), np.nan)
    idx = np.flatnonzero(used)
    for k in idx:
        keep = used.copy()
        keep[k] = False
        v = _fit(model, data.subset(keep), values, params)
        one = np.zeros(len(used), dtype=bool)
        one[k] = True
        held = data.subset(one)
        err = np.linalg.norm(_residuals(model, held, v).reshape(-1, 3), axis=1)
        out[k], out_rms[k] = float(err.mean()), math.sqrt(float(np.mean(err**2)))
    return out, out_rms


def _fle_rms_mm(r: F64, n_params: int) -> float:
    """RMS detection error per sphere (3-D) implied by the fit residuals: Σr² / (m − P) × 3."""
    return math.sqrt(3.0 * float(r @ r) / max(len(r) - n_params, 1))


def _registration_tre_rms_mm(fle_rms_mm: float, centres_phantom_mm: F64) -> float:
    from registration.quality import predicted_tre_mm

    tre = predicted_tre_mm(fle_rms_mm, centres_phantom_mm, centres_phantom_mm)
    return math.sqrt(float(np.mean(np.asarray(tre) ** 2)))


def _std_errors(jac: F64, r: F64) -> F64:
    """Standard errors from σ² (JᵀJ)⁻¹, σ² = Σr² / (m − P)."""
    dof = max(jac.shape[0] - jac.shape[1], 1)
    s2 = float(r @ r) / dof
    cov = np.linalg.pinv(np.einsum("ij,ik->jk", jac, jac)) * s2
    return np.asarray(np.sqrt(np.clip(np.diag(cov), 0.0, None)), dtype=np.float64)


def _stack(poses: Sequence[MatchedPose], centres_phantom_mm: F64) -> _Data:
    for p in poses:
        if len(p.sphere_indices) != len(p.centres_image_mm) or len(p.sphere_indices) < 3:
            raise CalibrationError(
                f"scan {p.name}: needs ≥ 3 matched spheres paired with centres, "
                f"got {len(p.sphere_indices)} indices / {len(p.centres_image_mm)} centres"
            )
    return _Data(
        np.stack([np.asarray(p.joints_rad, dtype=np.float64) for p in poses]),
        np.concatenate([centres_phantom_mm[p.sphere_indices] for p in poses]),
        np.concatenate([np.asarray(p.centres_image_mm, dtype=np.float64) for p in poses]),
        np.concatenate([np.full(len(p.sphere_indices), i, dtype=np.int64) for i, p in enumerate(poses)]),
    )


def _fit_without_outliers(
    model: _Model, data: _Data, poses: Sequence[MatchedPose], params: CalibrationParams
) -> tuple[F64, NDArray[np.bool_], tuple[F64, F64, list[F64]]]:
    """Fit all poses; flag poses whose RMS residual stands out, then refit without them (or refuse)."""
    values = _fit(model, data, np.zeros(len(model.params)), params)
    used = np.ones(len(poses), dtype=bool)
    rms, mx, per = _per_pose(model, data, values, len(poses))
    flagged = _outliers(rms, used, params)
    if flagged.any():
        names = [f"{poses[int(i)].name} (RMS {rms[i]:.3f} mm)" for i in np.flatnonzero(flagged)]
        if params.outliers == "refuse" or int((~flagged).sum()) < params.min_poses:
            raise OutlierPoseError(
                "scans inconsistent with the others (robot moved during the scan, wrong joints or a wrong "
                f"sphere match): {', '.join(names)}; median pose RMS {np.median(rms):.3f} mm. Rescan them"
            )
        used = ~flagged
        values = _fit(model, data.subset(used), values, params)
        rms, mx, per = _per_pose(model, data, values, len(poses))
    return values, used, (rms, mx, per)


# ---------------------------------------------------------------- MAP: priors, cross-validation, posterior

WORKING_POSES: Final = 40
"""Poses sampled over the working volume for the predicted error (and the refusal)."""
WORKING_SEED: Final = 20201202
"""Fixed: the working-volume sample is a property of the session, not a random draw per call."""


def _prior_weights(model: _Model, params: CalibrationParams, scale: float) -> F64 | None:
    """σ_d / (s σ_j) per parameter (0 for the flat-prior rod and placement); None for ``"ls"``."""
    if params.estimator == "ls":
        return None
    sig = np.array([PRIORS.sigma(p) for p in model.params])
    return np.where(np.isfinite(sig), params.data_sd_mm / (scale * np.where(np.isfinite(sig), sig, 1.0)), 0.0)


def _cross_validate(
    model: _Model, data: _Data, x0: F64, params: CalibrationParams
) -> tuple[float, dict[float, float]]:
    """Prior scale with the least mean squared sphere error on left-out poses (k-fold over poses).

    Each fold leaves out every ``cv_folds``-th pose, fits the rest (same O-arm placement, so the
    left-out poses are predicted with the fitted ``image_from_robot``) and scores the left-out
    detections.  Never sees the held-out poses of a benchmark."""
    n = len(data.joints_rad)
    k = max(2, min(params.cv_folds, n))
    folds = [np.arange(n) % k == f for f in range(k)]
    scores: dict[float, float] = {}
    for scale in params.prior_scales:
        m = model.with_prior(_prior_weights(model, params, scale))
        sq, cnt = 0.0, 0
        for f in folds:
            v = _fit(m, data.subset(~f), x0, params)
            r = _residuals(m, data.subset(f), v)
            sq += float(r @ r)
            cnt += len(r) // 3
        scores[scale] = sq / max(cnt, 1)
    return min(scores, key=lambda s_: scores[s_]), scores


def _posterior_cov(model: _Model, data: _Data, values: F64, params: CalibrationParams, scale: float) -> F64:
    """(JᵀJ / σ̂² + Σ_prior⁻¹)⁻¹: the Gauss–Newton posterior covariance of the estimate.

    σ̂² = Σr² / (m − P) from the sphere residuals (at least (1 µm)²).  The prior (robot parameters:
    :data:`PRIORS` × the cross-validated scale for ``"map"``, × 1 for ``"ls"``; rod and placement:
    :meth:`Priors.sigma_posterior`) bounds what the poses cannot see, so a direction they miss
    shows in the predicted error instead of vanishing in a pseudo-inverse."""
    jac = _jacobian(model, data, values)
    r = _residuals(model, data, values)
    s2 = max(float(r @ r) / max(len(r) - len(values), 1), 1e-6)
    sig = np.array([PRIORS.sigma_posterior(p) for p in model.params])
    robot = np.array([p.group not in ("image_from_robot", "tool0_from_phantom") for p in model.params])
    sig = np.where(robot, sig * (scale if math.isfinite(scale) else 1.0), sig)
    a = np.einsum("ij,ik->jk", jac, jac) / s2 + np.diag(1.0 / sig**2)
    d = np.sqrt(np.diag(a))
    return np.asarray(np.linalg.inv(a / np.outer(d, d)) / np.outer(d, d), dtype=np.float64)


def _skew_rows(p: F64) -> F64:
    """(3N, 6) Jacobian of a small rigid motion (ω, t) of points p (N, 3): ω × p + t."""
    n = len(p)
    g = np.zeros((n, 3, 6))
    g[:, 0, 1], g[:, 0, 2] = p[:, 2], -p[:, 1]
    g[:, 1, 0], g[:, 1, 2] = -p[:, 2], p[:, 0]
    g[:, 2, 0], g[:, 2, 1] = p[:, 1], -p[:, 0]
    g[:, :, 3:] = np.eye(3)
    return g.reshape(3 * n, 6)


def _effective_jacobians(model: _Model, values: F64, joints_rad: F64, reg_joints_rad: F64, pts: F64) -> F64:
    """(W, 3N, P) sphere-position Jacobians at ``joints_rad`` after a one-scan re-registration at
    ``reg_joints_rad``: J_q − G_q G_reg⁺ J_reg (the rigid part the registration absorbs removed)."""
    q = np.vstack([joints_rad, reg_joints_rad[None]])
    n = len(pts)
    data = _Data(q, np.tile(pts, (len(q), 1)), np.zeros((len(q) * n, 3)), np.repeat(np.arange(len(q)), n))
    jac = _jacobian(model, data, values).reshape(len(q), 3 * n, len(values))
    world = model.predict(values, q, data.pts_phantom_mm, data.pose_of).reshape(len(q), n, 3)
    g_reg = _skew_rows(world[-1])
    proj = np.linalg.pinv(g_reg) @ jac[-1]  # (6, P)
    g_q = np.stack([_skew_rows(w) for w in world[:-1]])  # (W, 3N, 6)
    return np.asarray(jac[:-1] - g_q @ proj, dtype=np.float64)


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
    rms_mm: float
    max_mm: float
    weak_direction: tuple[tuple[str, float], ...]
    """Parameters of the direction that dominates the worst pose's error, with their share."""
    exciting_joints_rad: F64
    """(≤ 3, n) poses inside the scan volume whose spheres move most along that direction."""


def _unmodelled_rms_mm(model: _Model, data: _Data, values: F64, fle_rms_mm: float) -> float:
    """RMS of the per-pose rigid part of the residuals beyond what FLE leaks into it: errors no
    geometric model has (repeatability, sag) as seen at the calibration poses."""
    r = _residuals(model, data, values).reshape(-1, 3)
    world = model.predict(values, data.joints_rad, data.pts_phantom_mm, data.pose_of)
    ms = []
    for i in range(len(data.joints_rad)):
        rows = data.pose_of == i
        if rows.sum() < 3:
            continue
        g = _skew_rows(world[rows])
        sol, *_ = np.linalg.lstsq(g, r[rows].reshape(-1), rcond=None)
        rigid = (g @ sol).reshape(-1, 3)
        ms.append(float(np.mean(np.sum(rigid**2, axis=1))) - 2.0 * fle_rms_mm**2 / int(rows.sum()))
    return math.sqrt(max(float(np.mean(ms)) if ms else 0.0, 0.0))


def predict_working_error(
    model: _Model,
    values: F64,
    cov: F64,
    working_joints_rad: F64,
    registration_joints_rad: F64,
    pts: F64,
    *,
    unmodelled_rms_mm: float,
    registration_tre_rms_mm: float,
    candidate_joints_rad: F64 | None = None,
) -> WorkingPrediction:
    """Posterior covariance propagated through the kinematics to the working poses (after a one-scan
    re-registration at ``registration_joints_rad``), plus √2 × the unmodelled error (at the
    pose and at the registration pose) and the registration's own TRE, in quadrature."""
    jeff = _effective_jacobians(model, values, working_joints_rad, registration_joints_rad, pts)
    n = len(pts)
    chain_ms = np.einsum("wip,pq,wiq->w", jeff, cov, jeff) / n
    chain_rms = np.sqrt(np.clip(chain_ms, 0.0, None))
    per = np.sqrt(chain_ms + 2.0 * unmodelled_rms_mm**2 + registration_tre_rms_mm**2)
    worst = int(np.argmax(per))
    lam, vec = np.linalg.eigh((cov + cov.T) / 2.0)
    lo = vec * np.sqrt(np.clip(lam, 0.0, None))
    _, _, vt = np.linalg.svd(jeff[worst] @ lo, full_matrices=False)
    direction = lo @ vt[0]
    share = np.abs(direction) / np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    share = share / share.sum()
    order = np.argsort(-share)[:4]
    weak = tuple((model.params[j].name, float(share[j])) for j in order)
    exciting = np.zeros((0, len(registration_joints_rad)))
    if candidate_joints_rad is not None and len(candidate_joints_rad):
        c = candidate_joints_rad
        data = _Data(c, np.tile(pts, (len(c), 1)), np.zeros((len(c) * n, 3)), np.repeat(np.arange(len(c)), n))
        jc = _jacobian(model, data, values).reshape(len(c), 3 * n, len(values))
        gain = np.linalg.norm(jc @ direction, axis=1)
        exciting = c[np.argsort(-gain)[:3]]
    return WorkingPrediction(
        working_joints_rad,
        registration_joints_rad,
        per,
        chain_rms,
        float(np.sqrt(np.mean(per**2))),
        float(per.max()),
        weak,
        exciting,
    )


def _farthest_split_inflation(
    model: _Model,
    data: _Data,
    values: F64,
    params: CalibrationParams,
    fle_rms_mm: float,
    unmodelled_rms_mm: float,
) -> tuple[float, tuple[int, ...]]:
    """How optimistic the posterior is away from the poses: hold out the poses farthest from the
    rest (largest RMS sphere distance to their nearest other pose, ⌈K/4⌉ of them, ≥ 2), fit the
    others, and compare the held-out poses' squared error (detection error removed) with what the
    split fit's posterior (+ unmodelled) predicts there.  Returns (k² ≥ 1, held-out pose indices)."""
    k = len(data.joints_rad)
    n_out = max(2, math.ceil(k / 4))
    if k - n_out < 3:
        return 1.0, ()
    world = model.predict(values, data.joints_rad, data.pts_phantom_mm, data.pose_of)
    pts = data.pts_phantom_mm[data.pose_of == 0]
    q = data.joints_rad
    full = _Data(q, np.tile(pts, (k, 1)), np.zeros((k * len(pts), 3)), np.repeat(np.arange(k), len(pts)))
    w = model.predict(values, q, full.pts_phantom_mm, full.pose_of).reshape(k, len(pts), 3)
    d = np.sqrt(np.mean(np.sum((w[:, None] - w[None]) ** 2, axis=-1), axis=-1))
    np.fill_diagonal(d, np.inf)
    out = tuple(int(i) for i in np.argsort(-d.min(axis=1))[:n_out])
    del world
    held = np.zeros(k, dtype=bool)
    held[list(out)] = True
    train = data.subset(~held)
    v = _fit(model, train, values, params)
    cov = _posterior_cov(model, train, v, params, 1.0)
    test = data.subset(held)
    r = _residuals(model, test, v).reshape(-1, 3)
    obs = float(np.mean(np.sum(r**2, axis=1))) - fle_rms_mm**2
    jac = _jacobian(model, test, v).reshape(len(r), 3, len(v))
    pred = float(np.mean(np.einsum("lip,pq,liq->l", jac, cov, jac))) + unmodelled_rms_mm**2
    if pred <= 0.0:
        return 1.0, out
    return max(1.0, obs / pred), out


def _default_volume(meas_image_mm: F64) -> ScanVolume:
    from registration.pose_sampling import ScanVolume

    d = ScanVolume()
    c = meas_image_mm.mean(axis=0)
    return ScanVolume(
        (float(c[0]), float(c[1]), float(c[2])), d.fov_radius_mm, d.half_length_mm, d.axis_image
    )


def _working_prediction(
    model: _Model,
    values: F64,
    cov: F64,
    data: _Data,
    pts: F64,
    params: CalibrationParams,
    scan_volume: ScanVolume | None,
    unmodelled_rms_mm: float,
    registration_tre_rms_mm: float,
) -> tuple[WorkingPrediction, dict[str, Any]]:
    """Sample the working volume (scan volume + margin) with the calibrated model and predict."""
    from registration.pose_sampling import sample_poses_in_volume

    y, x, cal_chain = model.unpack(values)
    vol = scan_volume if scan_volume is not None else _default_volume(data.meas_image_mm)
    work = vol.grown(params.working_margin_mm)
    rng = np.random.default_rng(WORKING_SEED)
    q0 = data.joints_rad[0]
    wq = sample_poses_in_volume(
        y,
        cal_chain,
        x,
        pts,
        q0,
        work,
        rng,
        n=WORKING_POSES,
        max_tilt_deg=75.0,
        margin_mm=0.0,
        n_candidates=300,
    )
    inside = sample_poses_in_volume(
        y, cal_chain, x, pts, q0, vol, rng, n=30, max_tilt_deg=75.0, margin_mm=5.0, n_candidates=300
    )
    if len(wq) == 0:
        wq = data.joints_rad
    if len(inside):
        centres = (y @ cal_chain.robot_from_tool0_batch(inside) @ x)[:, :3, 3]
        q_reg = inside[int(np.argmin(np.linalg.norm(centres - np.asarray(vol.centre_image_mm), axis=1)))]
    else:
        q_reg = q0
    pred = predict_working_error(
        model,
        values,
        cov,
        wq,
        q_reg,
        pts,
        unmodelled_rms_mm=unmodelled_rms_mm,
        registration_tre_rms_mm=registration_tre_rms_mm,
        candidate_joints_rad=inside,
    )
    doc = {
        "scan_volume": {
            "centre_image_mm": list(vol.centre_image_mm),
            "fov_radius_mm": vol.fov_radius_mm,
            "half_length_mm": vol.half_length_mm,
            "axis_image": list(vol.axis_image),
            "from": "series geometry"
            if scan_volume is not None
            else "default O-arm cylinder on the detections",
        },
        "margin_mm": params.working_margin_mm,
        "n_poses": len(wq),
    }
    return pred, doc


def _prediction_refusal(
    pred: WorkingPrediction, params: CalibrationParams, joints_rad: F64, names: Sequence[str]
) -> str:
    weak = ", ".join(f"{n} ({100 * v:.0f} %)" for n, v in pred.weak_direction)
    poses = "; ".join(
        "[" + ", ".join(f"{math.degrees(v):.1f}" for v in q) + "]" for q in pred.exciting_joints_rad
    )
    return (
        f"predicted error over the working volume (scan volume + {params.working_margin_mm:g} mm) up to "
        f"{pred.max_mm:.3f} mm RMS at the worst pose (mean {pred.rms_mm:.3f} mm) > the limit "
        f"{params.max_predicted_error_mm:g} mm; weak direction: {weak}. "
        + (f"Poses inside the scan volume that would excite it (joints in deg): {poses}. " if poses else "")
        + _motion_advice([], joints_rad, names)
    ).strip()


def calibrate(
    poses: Sequence[MatchedPose],
    chain: SerialChain,
    tool0_from_phantom: ArrayLike,
    centres_phantom_mm: ArrayLike,
    params: CalibrationParams = CalibrationParams(),
    scan_volume: ScanVolume | None = None,
) -> CalibrationResult:
    """Estimate ``image_from_robot``, ``tool0_from_phantom`` and joint-origin corrections.

    ``scan_volume``: the session's reconstructed cylinder (image frame); the working volume is it
    grown by ``params.working_margin_mm``.  None: the O-arm export's default cylinder
    (:class:`registration.pose_sampling.ScanVolume`) centred on the centroid of the detections.

    Parameters
    ----------
    poses : sequence of MatchedPose, length K ≥ ``params.min_poses``
    chain : SerialChain
        The nominal arm (:func:`registration.urdf_writer.read_chain`).
    tool0_from_phantom : array_like, shape (4, 4)
        Nominal rod (mm); only used to name the gauge — the fit starts from Shah's estimate.
    centres_phantom_mm : array_like, shape (N, 3)
        The phantom's sphere centres (CAD, mm), indexed by ``MatchedPose.sphere_indices``.
    params : CalibrationParams

    Returns
    -------
    CalibrationResult
        Calibrated chain (offsets folded into the origins), X, Y, parameters with standard
        errors, rank / condition number, per-pose and per-sphere residuals, outlier poses,
        leave-one-pose-out errors.

    Raises
    ------
    TooFewPosesError, SessionMismatchError, NotIdentifiableError, OutlierPoseError
    """
    t0 = time.perf_counter()
    as_transform(tool0_from_phantom, "tool0_from_phantom")
    check_session(poses, params.min_poses)
    pts = np.asarray(centres_phantom_mm, dtype=np.float64)
    data = _stack(poses, pts)
    y0, x0 = _initial_estimate(poses, chain, pts)
    # MAP puts its priors on the physical joint-origin errors (6 per joint, "all"): on the minimal set
    # the priors would sit on combinations that absorb the redundant errors (misspecified: 1.5 × the
    # LS error on the tuning seeds, measured), so "full" means "all" for the MAP estimator.
    pset = "all" if params.estimator == "map" and params.parameter_set == "full" else params.parameter_set
    model = _Model(y0, x0, chain, minimal_parameter_set(chain, pset))
    model, dropped, rank, cond, s = _select_parameters(model, data, params, chain.joint_names)
    model = model.with_prior(_prior_weights(model, params, 1.0))
    timings = {"start_s": time.perf_counter() - t0}
    t1 = time.perf_counter()
    values, used, (rms, mx, per) = _fit_without_outliers(model, data, poses, params)
    fit_data = data.subset(used)
    scale, cv = (float("nan"), None) if params.estimator == "ls" else (float(params.prior_scales[0]), None)
    if params.estimator == "map" and len(params.prior_scales) == 1:
        model = model.with_prior(_prior_weights(model, params, scale))
        values = _fit(model, fit_data, values, params)
        rms, mx, per = _per_pose(model, data, values, len(poses))
    if params.estimator == "map" and len(params.prior_scales) > 1:
        t_cv = time.perf_counter()
        scale, cv = _cross_validate(model, fit_data, values, params)
        timings["cross_validation_s"] = time.perf_counter() - t_cv
        model = model.with_prior(_prior_weights(model, params, scale))
        values = _fit(model, fit_data, values, params)
        rms, mx, per = _per_pose(model, data, values, len(poses))
    timings["solve_s"] = time.perf_counter() - t1
    jac = _jacobian(model, fit_data, values)
    r = _residuals(model, fit_data, values)
    rank, cond, s, weak, _ = _identifiability(jac, model.params, params.rank_rtol)
    limit = params.max_condition if params.max_condition is not None else math.inf
    if not used.all() and cond > limit and params.on_weak == "refuse":
        excluded = ", ".join(p.name for p, u in zip(poses, used, strict=True) if not u)
        advice = _motion_advice(weak, fit_data.joints_rad, chain.joint_names)
        raise NotIdentifiableError(
            f"without the outlier scans {excluded} the remaining poses no longer identify the parameters "
            f"(condition number {cond:.3g} > {limit:g}); rescan them. {advice}"
        )
    fle = _fle_rms_mm(r, len(model.params))
    reg_tre = _registration_tre_rms_mm(fle, pts)
    cov = _posterior_cov(model, fit_data, values, params, scale)
    unmod = max(_unmodelled_rms_mm(model, fit_data, values, fle), params.unmodelled_floor_mm)
    t_p = time.perf_counter()
    inflation, split = (
        _farthest_split_inflation(model, fit_data, values, params, fle, unmod)
        if params.farthest_split
        else (1.0, ())
    )
    prediction, volume_doc = _working_prediction(
        model,
        values,
        cov * inflation,
        fit_data,
        pts,
        params,
        scan_volume,
        unmod * math.sqrt(inflation),
        reg_tre,
    )
    volume_doc["farthest_split"] = {"poses": [int(i) for i in split], "variance_inflation": inflation}
    timings["prediction_s"] = time.perf_counter() - t_p
    if prediction.max_mm > params.max_predicted_error_mm:
        raise NotIdentifiableError(
            _prediction_refusal(prediction, params, fit_data.joints_rad, chain.joint_names)
        )
    t2 = time.perf_counter()
    nan = np.full(len(poses), np.nan)
    lopo, lopo_rms = _leave_one_out(model, data, values, used, params) if params.leave_one_out else (nan, nan)
    timings["leave_one_out_s"] = time.perf_counter() - t2
    y, x, cal_chain = model.unpack(values)
    return CalibrationResult(
        image_from_robot=y,
        tool0_from_phantom=x,
        chain=cal_chain,
        parameters=model.params,
        values=values,
        std_errors=np.sqrt(np.clip(np.diag(cov), 0.0, None)),
        rank=rank,
        condition_number=cond,
        singular_values=s,
        dropped=dropped,
        pose_names=tuple(p.name for p in poses),
        used=used,
        pose_rms_mm=rms,
        pose_max_mm=mx,
        sphere_residuals_mm=tuple(per),
        sphere_indices=tuple(np.asarray(p.sphere_indices, dtype=np.int64) for p in poses),
        outliers=tuple(poses[int(i)].name for i in np.flatnonzero(~used)),
        lopo_pose_mean_mm=lopo,
        lopo_pose_rms_mm=lopo_rms,
        timings_s=timings,
        fit_rms_mm=float(np.sqrt(np.mean(r**2) * 3.0)),
        fle_rms_mm=fle,
        registration_tre_rms_mm=reg_tre,
        estimator=params.estimator,
        prior_scale=scale,
        cv_scores=cv,
        posterior_cov=cov,
        unmodelled_rms_mm=unmod,
        prediction=prediction,
        working_volume=volume_doc,
    )


def match_pose(
    name: str,
    joints_rad: ArrayLike,
    centres_image_mm: ArrayLike,
    robot_mm: ArrayLike,
    *,
    phantom: Any = None,
    series_uid: str = "",
    frame_of_reference_uid: str = "",
) -> MatchedPose:
    """Match one scan's detections to the phantom's spheres with the click-free registration.

    ``robot_mm`` are the sphere centres by the *nominal* model and rod (their 1-mm error is far
    inside the registration's gates).  Errors of :func:`registration.register.register_points`
    are re-raised with the scan name.
    """
    from registration.register import register_points

    try:
        reg = register_points(robot_mm, centres_image_mm, phantom=phantom)
    except OarmRegError as e:
        raise type(e)(f"calibration scan {name}: {e}") from None
    img = np.asarray(centres_image_mm, dtype=np.float64)
    return MatchedPose(
        name=name,
        joints_rad=np.asarray(joints_rad, dtype=np.float64).reshape(-1),
        sphere_indices=reg.robot_indices.astype(np.int64),
        centres_image_mm=img[reg.image_indices],
        series_uid=series_uid,
        frame_of_reference_uid=frame_of_reference_uid,
    )


def predict_image_mm(
    result: CalibrationResult,
    joints_rad: ArrayLike,
    centres_phantom_mm: ArrayLike,
    image_from_robot: ArrayLike | None = None,
) -> F64:
    """Sphere centres (image mm) the calibration predicts at ``joints_rad`` (optionally another Y)."""
    y = result.image_from_robot if image_from_robot is None else as_transform(image_from_robot)
    t = y @ result.chain.robot_from_tool0(joints_rad) @ result.tool0_from_phantom
    pts = np.asarray(centres_phantom_mm, dtype=np.float64)
    return np.asarray(pts @ t[:3, :3].T + t[:3, 3], dtype=np.float64)


def chain_error_figure(calibration: Mapping[str, Any] | None) -> tuple[float, str]:
    """(predicted_chain_error_mm, its source) of a registration made with ``calibration``: the
    active calibration's posterior figure, else the nominal model's prior (issue #20)."""
    if calibration is not None:
        v = calibration.get("predicted_chain_error_mm")
        if v is not None:
            return float(v), f"calibration {calibration.get('calibration_id')} posterior"
        return NOMINAL_CHAIN_ERROR_MM, (
            f"calibration {calibration.get('calibration_id')} has no posterior figure "
            "(made before issue #20): nominal prior"
        )
    return NOMINAL_CHAIN_ERROR_MM, "nominal model prior (no active calibration)"
