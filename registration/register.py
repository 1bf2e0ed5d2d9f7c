"""From sphere centres to ``image_from_robot``: correspondence, ICP, symmetry and quality checks.

:func:`register_points` is the contract (brief "Registration"):

1. the robot configuration is checked (collinear / coplanar refused);
2. candidate poses come from the click-free triple search
   (:func:`registration.correspondence.find_hypotheses`), or from the paper's
   four-mark pre-registration (eq. 7, :mod:`registration.prereg`) when
   ``prereg_pairs`` are given;
3. an orientation prior, if any, discards poses rotated further than its
   tolerance (< 45°, half the 90° symmetry of the hole grid: research §1.6);
4. the best candidates and, when a :class:`~registration.phantom.Phantom` is
   given, every symmetry twin of the best pose are refined by gated ICP
   (:mod:`registration.icp`); the best must explain at least
   ``min_runner_up_margin`` more spheres than the best *distinct* runner-up or
   the result is refused as ambiguous (design.md §4).  On a subset (at most
   ``exhaustive_runner_up_max_points`` detections) the runner-up comes from an
   exhaustive triple search
   (:func:`registration.correspondence.exhaustive_runner_ups`), not only from
   the hypotheses that found the best pose;
5. the mirrored problem (image z → −z) is tried whenever it could explain
   clearly more spheres; if it does, the input is refused as mirrored;
6. quality figures (design.md §5) are computed and gated.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any, Final

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from registration import __version__
from registration.correspondence import (
    DEFAULT_DISTINCT_ROTATION_DEG,
    DEFAULT_DISTINCT_TRANSLATION_MM,
    Hypothesis,
    exhaustive_runner_ups,
    find_hypotheses,
    same_pose,
)
from registration.errors import (
    AccuracyGateError,
    AmbiguousMatchError,
    ConfigError,
    ImproperRotationError,
    MirroredInputError,
    OarmRegError,
    RegistrationError,
    TooFewSpheresError,
    TooFewWithinGateError,
)
from registration.icp import IcpResult, icp
from registration.phantom import Phantom
from registration.prereg import PreregResult, preregister
from registration.quality import (
    Conditioning,
    check_configuration,
    fle_from_fre,
    predicted_tre_mm,
)
from registration.rigid import fit_rigid, rotation_difference_deg

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

MAX_PRIOR_TOLERANCE_DEG: Final = 45.0
"""An orientation prior must be tighter than half the 90° grid symmetry to separate twins."""

PHANTOM_FIT_MAX_RMS_MM: Final = 1.0
"""The robot points must match the phantom's CAD centres within this RMS (mm) for the phantom's
symmetry twins to be tried; otherwise the robot points are not this phantom's."""


PRIOR_ROTATION_TOL: Final = 1e-3
"""An orientation prior is a rotation if RᵀR = I and det R = 1 within this: a matrix written with 4
decimals (a hand-typed prior) passes, a scaled or sheared one does not."""

DET_TOL: Final = 1e-9
"""det R of the result must be 1 within this: Kabsch with the determinant fix gives 1 to rounding."""


class PointSetError(OarmRegError):
    """A point set passed to the registration has the wrong shape or non-finite values."""

    title = "Invalid point set"


class PriorMismatchError(RegistrationError):
    """No pose within the orientation prior's tolerance explains the detections."""

    title = "Orientation prior not met"


@dataclass(frozen=True)
class RegistrationParams:
    """Tolerances and gates of :func:`register_points` (lengths in mm, angles in degrees).

    The service may override any of them from TOML.
    """

    min_matched: int = 6
    """Fewest matched spheres accepted (a rigid fit needs 3; 6 leaves FLE/FRE meaningful, N−2 ≥ 4)."""
    min_runner_up_margin: int = 3
    """Matched spheres by which the best pose must beat the best distinct runner-up (research §1.6:
    m ≥ 3, so that one or two missed detections cannot flip the answer)."""
    max_fre_mm: float = 0.5
    """FRE gate, the value of ``quality.max_fre_mm`` in configs/oarmreg.toml (one source of truth:
    service/settings.py takes its default from here).  Simulated FRE is ≈ 0.1 mm (σ 0.05 mm image,
    0.02 mm robot); the paper's phantom is machined to ±0.02 mm (Bai 2018 §2.1); 0.5 mm leaves room
    for real-scanner noise while rejecting a one-pitch (15 mm) mismatch or a wrong joint reading.
    Research §2 measures 0.6 mm at σ = 0.25 mm per axis per space: such data needs a larger gate."""
    pair_distance_tol_mm: float = 1.0
    """Two inter-sphere distances agree when closer than this.  A distance difference has sd ≈ 2σ
    (σ√2 per space for σ per axis); 4 × 2 × σ with σ = 0.1 mm is 0.8 mm, + margin → 1 mm."""
    hypothesis_gate_mm: float = 1.5
    """Inlier gate for 3-point hypotheses: their pose error at 100 mm lever with σ = 0.25 mm and
    ≥ 45 mm edges is ≈ 0.7 mm, ×2 margin; far below half the 15 mm pitch."""
    max_base_triples: int = 12
    """Base triples searched at most: disjoint ones first (≤ 3 missing spheres spoil at most 3 of
    them), then overlapping ones for scans with many missing spheres.  The search stops as soon as
    ``min_agreeing_triples`` agree, so the usual scan uses two or three."""
    min_agreeing_triples: int = 2
    """The search stops once the best pose was found from this many independent base triples."""
    distinct_rotation_deg: float = DEFAULT_DISTINCT_ROTATION_DEG
    """Two poses are distinct if their rotations differ by more than this (the grid's symmetries are
    ≥ 90° apart; 3-point pose noise is ≈ 0.1°); also find_hypotheses' default."""
    distinct_translation_mm: float = DEFAULT_DISTINCT_TRANSLATION_MM
    """... or if the robot centroid lands more than this apart (one pitch is 15 mm)."""
    max_runner_ups: int = 3
    """Distinct runner-up candidates refined by ICP (plus ``max_refined_twins``)."""
    max_refined_twins: int = 8
    """Further poses refined by ICP on top of ``max_runner_ups``: room for every phantom symmetry twin
    (a 70 × 70 × 80 mm cuboid has 8 proper symmetries, design.md §4)."""
    threat_margin_factor: int = 2
    """A competing pose is refined by ICP only if its unrefined count comes within this ×
    ``min_runner_up_margin`` of the best; one further behind cannot threaten the answer (ICP adds a
    sphere or two to a 3-point pose's count, not 2 × 3), and its count still bounds the runner-up."""
    exhaustive_runner_up_max_points: int = 16
    """Scans with at most this many detections (a subset of the phantom, or a small phantom) take
    their runner-up from :func:`registration.correspondence.exhaustive_runner_ups`: every image
    triple × every robot triple of matching sides.  find_hypotheses' few base triples with an early
    stop find the best pose but can miss a close runner-up on a subset (issue: 8 of the cube's 28
    spheres, runner-up 6 found as 4).  C(16, 3) = 560 image triples cost ≈ 0.3 s on the 2-core
    development machine against the 28-sphere cube (6: ≈ 20 ms, 8: ≈ 30 ms, 12: ≈ 0.1 s); a
    larger subset (fewer detections than robot spheres) is searched exhaustively too, but only when
    the runner-up found otherwise comes within ``threat_margin_factor × min_runner_up_margin``."""
    icp_gate_start_mm: float = 7.5
    """Half the 15 mm hole pitch (research §1.7)."""
    icp_gate_sigma_factor: float = 3.0
    """The ICP gate shrinks to this × the robust RMS residual (research §1.7: "~3σ_FRE")."""
    icp_gate_floor_mm: float = 0.3
    """Smallest ICP gate (≈ 3 × simulated FRE); spurious blobs are > 2 mm from spheres."""
    icp_max_iterations: int = 50
    icp_tol_mm: float = 1e-7
    """ICP stops when no sphere moves by more than this between iterations."""
    min_collinear_ratio: float = 1e-3
    """λ2/λ1 below this = collinear spheres (see registration.quality)."""
    min_coplanar_ratio: float = 1e-3
    """λ3/λ1 below this = coplanar spheres (see registration.quality)."""
    mirror_axis: int = 2
    """Image axis negated to build the mirrored problem (2 = z, the slice axis most often flipped)."""
    mirror_min_fraction: float = 0.75
    """The mirrored problem must explain this fraction of min(expected, detected) spheres to call the
    input mirrored: the cube grid is achiral, so a mirror image of a filled pattern still overlaps
    the proper pattern partly (14 of 28 spheres for bai2018_cube) and must not win by default."""
    verify_gate_mm: float = 5.0
    """Verification pairs a predicted sphere with a detection within this distance: large enough to
    report a registration error of several mm honestly, below half the pitch so pairs stay unique."""


@dataclass(frozen=True, eq=False)
class RegistrationResult:
    """A registration that passed every check.

    Attributes
    ----------
    image_from_robot : ndarray, shape (4, 4), float64
        p_image = image_from_robot @ p_robot (LPS mm ← robot mm).
    fre_mm, fle_mm : float
        RMS residual over the matched spheres and the FLE it implies (Fitzpatrick 1998 eq. 10).
    robot_indices, image_indices : ndarray, shape (K,), int64
        Matched pairs: index into the robot list (phantom sphere order) and into the detections.
    residuals_mm : ndarray, shape (K,), float64
    n_expected, n_detected, n_matched : int
    predicted_tre_mm : ndarray, shape (T,), float64
        Fitzpatrick eq. 46 at ``targets_robot_mm``; empty if no targets.
    symmetry_margin : int
        matched(best) − matched(best distinct runner-up).
    rotation_det : float
        det R (always +1).
    timings_s : dict
    """

    image_from_robot: F64
    fre_mm: float
    fle_mm: float
    robot_indices: I64
    image_indices: I64
    residuals_mm: F64
    n_expected: int
    n_detected: int
    n_matched: int
    predicted_tre_mm: F64
    symmetry_margin: int
    rotation_det: float
    timings_s: dict[str, float]
    robot_mm: F64 = field(default_factory=lambda: np.empty((0, 3)))
    image_mm: F64 = field(default_factory=lambda: np.empty((0, 3)))
    targets_robot_mm: F64 = field(default_factory=lambda: np.empty((0, 3)))
    runner_up_matched: int = 0
    runner_up_rotation_deg: float | None = None
    runner_up_source: str = ""
    method: str = "triples+icp"
    n_icp_iterations: int = 0
    collinearity: float = 0.0
    planarity: float = 0.0
    prior_angle_deg: float | None = None
    prereg: PreregResult | None = None
    mirror_checked: bool = False
    provenance: Mapping[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict: the ``oarmreg register --json`` format."""
        spheres = [
            {
                "index": int(r),
                "image_index": int(i),
                "robot_mm": [float(v) for v in self.robot_mm[r]] if len(self.robot_mm) else None,
                "image_mm": [float(v) for v in self.image_mm[i]] if len(self.image_mm) else None,
                "residual_mm": float(e),
            }
            for r, i, e in zip(self.robot_indices, self.image_indices, self.residuals_mm, strict=True)
        ]
        out: dict[str, Any] = {
            "image_from_robot": [[float(v) for v in row] for row in self.image_from_robot],
            "fre_mm": self.fre_mm,
            "fle_mm": self.fle_mm,
            "n_expected": self.n_expected,
            "n_detected": self.n_detected,
            "n_matched": self.n_matched,
            "spheres": spheres,
            "max_residual_mm": float(np.max(self.residuals_mm)) if len(self.residuals_mm) else None,
            "targets_robot_mm": [[float(v) for v in t] for t in self.targets_robot_mm],
            "predicted_tre_mm": [float(v) for v in self.predicted_tre_mm],
            "symmetry_margin": self.symmetry_margin,
            "runner_up_matched": self.runner_up_matched,
            "runner_up_rotation_deg": self.runner_up_rotation_deg,
            "runner_up_source": self.runner_up_source,
            "rotation_det": self.rotation_det,
            "method": self.method,
            "n_icp_iterations": self.n_icp_iterations,
            "conditioning": {"collinearity": self.collinearity, "planarity": self.planarity},
            "prior_angle_deg": self.prior_angle_deg,
            "mirror_checked": self.mirror_checked,
            "timings_s": dict(self.timings_s),
            "provenance": dict(self.provenance),
        }
        if self.prereg is not None:
            out["prereg"] = {
                "affine": [[float(v) for v in row] for row in self.prereg.affine],
                "nonrigidity": self.prereg.nonrigidity,
                "singular_values": [float(v) for v in self.prereg.singular_values],
                "rms_mm": self.prereg.rms_mm,
                "max_distance_mismatch_mm": self.prereg.max_distance_mismatch_mm,
            }
        return out


def params_dict(params: RegistrationParams) -> dict[str, Any]:
    """The parameters as a plain dict (for provenance)."""
    return asdict(params)


def _as_points(a: ArrayLike, name: str) -> F64:
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise PointSetError(
            f"{name}: expected an (N, 3) array of sphere centres in mm, got shape {arr.shape}"
        )
    if not np.all(np.isfinite(arr)):
        bad = np.flatnonzero(~np.all(np.isfinite(arr), axis=1))
        raise PointSetError(f"{name}: rows {bad[:5].tolist()} contain NaN or infinite values")
    return arr


def _as_rotation(prior: ArrayLike) -> F64:
    m = np.asarray(prior, dtype=np.float64)
    if m.shape == (4, 4):
        m = m[:3, :3]
    if m.shape != (3, 3) or not np.all(np.isfinite(m)):
        raise ConfigError(f"orientation prior: expected a 3 × 3 rotation (or 4 × 4 transform), got {m.shape}")
    if (
        np.max(np.abs(m.T @ m - np.eye(3))) > PRIOR_ROTATION_TOL
        or abs(np.linalg.det(m) - 1.0) > PRIOR_ROTATION_TOL
    ):
        raise ConfigError(
            f"orientation prior is not a proper rotation (det = {np.linalg.det(m):.4f}); give the "
            "expected rotation of image_from_robot"
        )
    return m


def _twins(best: F64, robot_mm: F64, phantom: Phantom | None) -> list[tuple[str, F64]]:
    """best ∘ each phantom symmetry, expressed as image_from_robot poses."""
    if phantom is None:
        return []
    ph = phantom.centres_phantom_mm
    if len(ph) != len(robot_mm):
        log.warning(
            "phantom %s has %d spheres but %d robot points were given; symmetry twins not tried "
            "(the runtime runner-up check still applies)",
            phantom.name,
            len(ph),
            len(robot_mm),
        )
        return []
    robot_from_phantom = fit_rigid(ph, robot_mm)
    rms = float(
        np.sqrt(
            np.mean(
                np.sum(
                    (ph @ robot_from_phantom[:3, :3].T + robot_from_phantom[:3, 3] - robot_mm) ** 2, axis=1
                )
            )
        )
    )
    if rms > PHANTOM_FIT_MAX_RMS_MM:
        log.warning(
            "robot points do not match phantom %s (RMS %.2f mm > %.1f mm); symmetry twins not tried",
            phantom.name,
            rms,
            PHANTOM_FIT_MAX_RMS_MM,
        )
        return []
    phantom_from_robot = np.linalg.inv(robot_from_phantom)
    out = []
    for sym in phantom.symmetries():
        s4 = np.eye(4)
        s4[:3, :3] = sym.rotation
        out.append(
            (f"phantom symmetry {sym.describe()}", best @ robot_from_phantom @ s4 @ phantom_from_robot)
        )
    return out


@dataclass
class _Candidate:
    """A pose in the competition: refined by ICP, or only counted (cannot threaten the best)."""

    source: str
    image_from_robot: F64
    n_matched: int
    rms_mm: float
    result: IcpResult | None = None


def _key(c: _Candidate) -> tuple[int, float]:
    return (c.n_matched, -c.rms_mm)


def _refined(source: str, res: IcpResult) -> _Candidate:
    return _Candidate(source, res.image_from_robot, res.n_matched, res.rms_mm, res)


def _quick_count(t: F64, robot_mm: F64, tree: cKDTree, gate_mm: float) -> tuple[int, float]:
    """Spheres landing within ``gate_mm`` of a detection under pose ``t`` (no refinement)."""
    d, _ = tree.query(robot_mm @ t[:3, :3].T + t[:3, 3], distance_upper_bound=gate_mm)
    ok = np.isfinite(d)
    n = int(ok.sum())
    return n, float(np.sqrt(np.mean(d[ok] ** 2))) if n else float("inf")


def _refine(robot_mm: F64, image_mm: F64, tree: cKDTree, init: F64, p: RegistrationParams) -> IcpResult:
    return icp(
        robot_mm,
        image_mm,
        init,
        tree=tree,
        gate_start_mm=p.icp_gate_start_mm,
        gate_sigma_factor=p.icp_gate_sigma_factor,
        gate_floor_mm=p.icp_gate_floor_mm,
        max_iterations=p.icp_max_iterations,
        tol_mm=p.icp_tol_mm,
    )


def _hypotheses(robot_mm: F64, image_mm: F64, tree: cKDTree, p: RegistrationParams) -> list[Hypothesis]:
    return find_hypotheses(
        robot_mm,
        image_mm,
        pair_tol_mm=p.pair_distance_tol_mm,
        gate_mm=p.hypothesis_gate_mm,
        max_base_triples=p.max_base_triples,
        min_agreeing=p.min_agreeing_triples,
        distinct_rotation_deg=p.distinct_rotation_deg,
        distinct_translation_mm=p.distinct_translation_mm,
        tree=tree,
    )


def _best_mirrored(robot_mm: F64, image_mm: F64, p: RegistrationParams) -> int:
    """Matched count of the best pose of the mirrored problem (image axis ``p.mirror_axis`` negated)."""
    mirrored = image_mm.copy()
    mirrored[:, p.mirror_axis] *= -1.0
    tree = cKDTree(mirrored)
    hyps = _hypotheses(robot_mm, mirrored, tree, p)
    if not hyps:
        return 0
    refined = _refine(robot_mm, mirrored, tree, hyps[0].image_from_robot, p).image_from_robot
    return max(hyps[0].n_inliers, _quick_count(refined, robot_mm, tree, p.hypothesis_gate_mm)[0])


# ----------------------------------------------------------------------------- the steps
# register_points runs these in order; each refuses with its own typed error.


@dataclass(frozen=True, eq=False)
class RegistrationInputs:
    """The validated inputs of :func:`register_points`."""

    robot: F64
    image: F64
    targets: F64
    prior: F64 | None
    prior_tolerance_deg: float
    prereg_pairs: tuple[tuple[int, int], ...] | None

    @property
    def n(self) -> int:
        return len(self.robot)

    @property
    def m(self) -> int:
        return len(self.image)


def _prereg_pairs(pairs_in: Sequence[tuple[int, int]], n: int, m: int) -> tuple[tuple[int, int], ...]:
    pairs = tuple((int(a), int(b)) for a, b in pairs_in)
    if len(pairs) != 4:
        raise PointSetError(f"pre-registration needs exactly 4 (robot, image) index pairs, got {len(pairs)}")
    ri = [a for a, _ in pairs]
    ii = [b for _, b in pairs]
    if min(ri) < 0 or max(ri) >= n or min(ii) < 0 or max(ii) >= m:
        raise PointSetError(
            f"pre-registration pairs {list(pairs)}: robot indices must be in 0..{n - 1}, "
            f"image indices in 0..{m - 1}"
        )
    if len(set(ri)) != 4 or len(set(ii)) != 4:
        raise PointSetError(f"pre-registration pairs {list(pairs)}: each sphere may be named only once")
    return pairs


def validate_inputs(
    robot_mm: ArrayLike,
    image_mm: ArrayLike,
    params: RegistrationParams,
    *,
    targets_robot_mm: ArrayLike | None = None,
    orientation_prior: ArrayLike | None = None,
    prior_tolerance_deg: float = 30.0,
    prereg_pairs: Sequence[tuple[int, int]] | None = None,
) -> RegistrationInputs:
    """Step 1: arrays, robot configuration, detection count, prior and pre-registration marks.

    Raises PointSetError, DegenerateConfigurationError, TooFewSpheresError (< 3 detections) or
    ConfigError (prior not a rotation, tolerance not below 45°).
    """
    p = params
    robot = _as_points(robot_mm, "robot points")
    image = _as_points(image_mm, "image points")
    n, m = len(robot), len(image)
    targets = (
        np.empty((0, 3))
        if targets_robot_mm is None
        else _as_points(np.reshape(targets_robot_mm, (-1, 3)), "targets")
    )
    check_configuration(
        robot,
        "robot points",
        min_collinear_ratio=p.min_collinear_ratio,
        min_coplanar_ratio=p.min_coplanar_ratio,
    )
    if m < 3:
        raise TooFewSpheresError(
            f"{m} sphere(s) detected, {n} expected: a registration needs at least {p.min_matched} matched "
            "spheres. Check that the phantom is inside the scanned volume and the detection threshold"
        )
    prior = None if orientation_prior is None else _as_rotation(orientation_prior)
    if not 0.0 < prior_tolerance_deg < MAX_PRIOR_TOLERANCE_DEG:
        raise ConfigError(
            f"orientation prior tolerance must be in (0, {MAX_PRIOR_TOLERANCE_DEG:g})°, got "
            f"{prior_tolerance_deg:g}°: the hole grid repeats every 90°"
        )
    pairs = None if prereg_pairs is None else _prereg_pairs(prereg_pairs, n, m)
    return RegistrationInputs(robot, image, targets, prior, float(prior_tolerance_deg), pairs)


@dataclass
class CandidatePool:
    """Every pose that competed, and the best of them (None if no consistent triple exists)."""

    best: _Candidate | None
    pool: list[_Candidate]
    hyps_all: list[Hypothesis]
    """Hypotheses of any orientation (the mirror check and the prior refusal look at them)."""
    hyps: list[Hypothesis]
    """Hypotheses within the prior's tolerance."""
    prereg: PreregResult | None
    prior: F64 | None
    """The given prior, or the pre-registration's rotation when none was given."""


def within_prior(t: F64, prior: F64 | None, tolerance_deg: float) -> bool:
    """True if pose ``t``'s rotation is within ``tolerance_deg`` of ``prior`` (always, without one)."""
    return prior is None or rotation_difference_deg(t[:3, :3], prior) <= tolerance_deg


def _competitors(
    best: _Candidate,
    hyps: list[Hypothesis],
    skip_first: bool,
    inp: RegistrationInputs,
    prior: F64 | None,
    tree: cKDTree,
    p: RegistrationParams,
    phantom: Phantom | None,
) -> list[tuple[str, F64, int, float]]:
    """(source, pose, count, rms) of every pose competing with ``best``, most spheres first."""
    others: list[tuple[str, F64, int, float]] = [
        (f"candidate {k}", h.image_from_robot, h.n_inliers, h.rms_mm)
        for k, h in enumerate(hyps)
        if k > 0 or not skip_first
    ]
    for name, twin in _twins(best.image_from_robot, inp.robot, phantom):
        if within_prior(twin, prior, inp.prior_tolerance_deg):
            n_q, rms_q = _quick_count(twin, inp.robot, tree, p.hypothesis_gate_mm)
            others.append((name, twin, n_q, rms_q))
    others.sort(key=lambda o: (o[2], -o[3]), reverse=True)
    return others


def _compete(
    best: _Candidate,
    others: list[tuple[str, F64, int, float]],
    inp: RegistrationInputs,
    tree: cKDTree,
    p: RegistrationParams,
    *,
    best_is_fixed: bool,
) -> tuple[_Candidate, list[_Candidate]]:
    """Refine the poses that threaten ``best`` by ICP, count the rest; return (best, the competitors).

    A pose is refined only if it comes within ``threat_margin_factor × min_runner_up_margin`` of the
    best (at most ``max_runner_ups + max_refined_twins`` of them).  ``best_is_fixed``: the named
    pre-registration marks define the pose, the others only compete as runner-ups.
    """
    pool: list[_Candidate] = []
    n_refined = 0
    for name, t_o, n_o, rms_o in others:
        threat = n_o + p.threat_margin_factor * p.min_runner_up_margin >= best.n_matched
        if threat and n_refined < p.max_runner_ups + p.max_refined_twins:
            n_refined += 1
            cand = _refined(name, _refine(inp.robot, inp.image, tree, t_o, p))
        else:
            cand = _Candidate(name, t_o, n_o, rms_o)
        pool.append(cand)
        if not best_is_fixed and _key(cand) > _key(best):
            best = cand
    return best, pool


def candidate_pool(
    inp: RegistrationInputs,
    tree: cKDTree,
    p: RegistrationParams,
    phantom: Phantom | None,
    timings: dict[str, float],
) -> CandidatePool:
    """Step 2: pre-registration (paper eq. 7) if marks are given, the click-free hypotheses, the
    phantom's symmetry twins, and ICP on the best and on every pose that threatens it.

    Raises DegenerateConfigurationError (coplanar marks) from the pre-registration.
    """
    prereg: PreregResult | None = None
    pool: list[_Candidate] = []
    prior = inp.prior
    if inp.prereg_pairs is not None:
        t0 = time.perf_counter()
        ri = [a for a, _ in inp.prereg_pairs]
        ii = [b for _, b in inp.prereg_pairs]
        prereg = preregister(inp.robot[ri], inp.image[ii])
        pool.append(
            _refined("pre-registration", _refine(inp.robot, inp.image, tree, prereg.image_from_robot, p))
        )
        timings["prereg_s"] = time.perf_counter() - t0
        if prior is None:
            prior = prereg.image_from_robot[:3, :3]

    t0 = time.perf_counter()
    hyps_all = _hypotheses(inp.robot, inp.image, tree, p)
    hyps = [h for h in hyps_all if within_prior(h.image_from_robot, prior, inp.prior_tolerance_deg)]
    timings["correspondence_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    best: _Candidate | None = None
    if prereg is not None:
        best = pool[0]
    elif hyps:
        best = _refined("candidate 0", _refine(inp.robot, inp.image, tree, hyps[0].image_from_robot, p))
        pool.append(best)
    if best is not None:
        others = _competitors(best, hyps, prereg is None, inp, prior, tree, p, phantom)
        best, competitors = _compete(best, others, inp, tree, p, best_is_fixed=prereg is not None)
        pool.extend(competitors)
    timings["icp_s"] = time.perf_counter() - t0
    return CandidatePool(best, pool, hyps_all, hyps, prereg, prior)


def check_mirror(inp: RegistrationInputs, cands: CandidatePool, tree: cKDTree, p: RegistrationParams) -> bool:
    """Step 3: refuse a mirrored input; True if the mirrored problem was tried.

    Handedness is independent of the prior: the best proper pose of any orientation is compared.
    Both sides are counted at the fixed hypothesis gate, not at ICP's self-adapted one: a proper fit
    of mirrored data is loose, and a gate grown from its own residuals would flatter it.  The proper
    problem "fails" when it would be refused for too few spheres; then a mirrored problem that
    succeeds is reported as such even without the full margin.

    Raises MirroredInputError.
    """
    n, m = inp.n, inp.m
    best = cands.best
    n_best = max(
        _quick_count(best.image_from_robot, inp.robot, tree, p.hypothesis_gate_mm)[0]
        if best is not None
        else 0,
        cands.hyps_all[0].n_inliers if cands.hyps_all else 0,
    )
    proper_fails = best is None or best.n_matched < p.min_matched
    if not (proper_fails or n_best + p.min_runner_up_margin <= min(n, m)):
        return False
    n_mirror = _best_mirrored(inp.robot, inp.image, p)
    if (
        (n_mirror >= n_best + p.min_runner_up_margin or (proper_fails and n_mirror > n_best))
        and n_mirror >= p.min_matched
        and n_mirror >= p.mirror_min_fraction * min(n, m)
    ):
        raise MirroredInputError(
            f"the image point set matches the robot points only as a mirror image ({n_mirror} of {n} "
            f"spheres match the mirrored image, {n_best} the image as given): check slice order / "
            "ImageOrientationPatient / a flipped axis in the export"
        )
    return True


def check_enough_matched(
    inp: RegistrationInputs, cands: CandidatePool, p: RegistrationParams
) -> tuple[_Candidate, IcpResult]:
    """Step 4: the best pose must be ICP-refined and match ``min_matched`` spheres.

    Raises PriorMismatchError (a pose outside the prior would have matched) or TooFewSpheresError.
    """
    best = cands.best
    if best is not None and best.result is not None and best.n_matched >= p.min_matched:
        return best, best.result
    n, m = inp.n, inp.m
    n_matched = 0 if best is None else best.n_matched
    if cands.prior is not None and cands.hyps_all and not cands.hyps:
        top = cands.hyps_all[0]
        angle = rotation_difference_deg(top.image_from_robot[:3, :3], cands.prior)
        if top.n_inliers >= p.min_matched:
            raise PriorMismatchError(
                f"no pose within {inp.prior_tolerance_deg:g}° of the orientation prior explains the "
                "detections; "
                f"the best pose ({top.n_inliers} of {n} spheres) is {angle:.1f}° away from the prior. "
                "Check the prior rotation (it is image_from_robot's rotation) or the "
                "pre-registration marks"
            )
    raise TooFewSpheresError(
        f"only {n_matched} sphere(s) matched ({n} expected, {m} detected, {p.min_matched} needed). "
        "Check that the robot points belong to this scan (same phantom, same pose), that the phantom "
        "is inside the scanned volume, and the detection result"
    )


@dataclass(frozen=True, eq=False)
class RunnerUp:
    """The best pose against the best *distinct* runner-up, both counted at the fixed gate."""

    n_best: int
    candidate: _Candidate | None
    n_matched: int
    rotation_deg: float | None

    @property
    def margin(self) -> int:
        return self.n_best - self.n_matched


def find_runner_up(
    best: _Candidate, pool: Sequence[_Candidate], robot: F64, tree: cKDTree, p: RegistrationParams
) -> RunnerUp:
    """The best pose of ``pool`` that is distinct from ``best`` (same_pose), by count at the fixed gate.

    Every pose is counted at the same fixed gate: ICP's gate adapts to each pose's own residuals,
    so a wrong pose refined by ICP would be flattered by its loose matches.
    """
    t_best = best.image_from_robot
    n_best = _quick_count(t_best, robot, tree, p.hypothesis_gate_mm)[0]
    centroid = robot.mean(axis=0)
    runner: _Candidate | None = None
    runner_key: tuple[int, float] = (-1, 0.0)
    for c in pool:
        if c is best or same_pose(
            t_best, c.image_from_robot, centroid, p.distinct_rotation_deg, p.distinct_translation_mm
        ):
            continue
        n_c, rms_c = _quick_count(c.image_from_robot, robot, tree, p.hypothesis_gate_mm)
        if (n_c, -rms_c) > runner_key:
            runner, runner_key = c, (n_c, -rms_c)
    angle = rotation_difference_deg(t_best[:3, :3], runner.image_from_robot[:3, :3]) if runner else None
    return RunnerUp(n_best, runner, max(runner_key[0], 0), angle)


def exhaustive_candidates(
    best: _Candidate,
    pool: Sequence[_Candidate],
    inp: RegistrationInputs,
    prior: F64 | None,
    tree: cKDTree,
    p: RegistrationParams,
) -> list[_Candidate]:
    """Step 5a: runner-up poses from the exhaustive triple search, for subsets and small sets.

    Runs when the image has at most ``exhaustive_runner_up_max_points`` detections, or fewer
    detections than robot spheres and a runner-up in ``pool`` within ``threat_margin_factor ×
    min_runner_up_margin`` of the best; otherwise returns nothing.  Each pose within the prior
    counts as found (3-point pose, fixed gate, as an independent brute-force search would count it);
    the ones that threaten the best (at most ``max_runner_ups``) are also refined by the same gated
    ICP as every other runner-up, so the comparison is like for like.
    """
    subset = inp.m < inp.n
    small = inp.m <= p.exhaustive_runner_up_max_points
    if not small:
        if not subset:
            return []
        ru = find_runner_up(best, pool, inp.robot, tree, p)
        if ru.margin >= p.threat_margin_factor * p.min_runner_up_margin:
            return []
    hyps = exhaustive_runner_ups(
        inp.robot,
        inp.image,
        best.image_from_robot,
        pair_tol_mm=p.pair_distance_tol_mm,
        gate_mm=p.hypothesis_gate_mm,
        distinct_rotation_deg=p.distinct_rotation_deg,
        distinct_translation_mm=p.distinct_translation_mm,
        tree=tree,
    )
    hyps = [h for h in hyps if within_prior(h.image_from_robot, prior, inp.prior_tolerance_deg)]
    out: list[_Candidate] = []
    for k, h in enumerate(hyps):
        name = f"exhaustive search pose {k}"
        out.append(_Candidate(name, h.image_from_robot, h.n_inliers, h.rms_mm))
        threat = h.n_inliers + p.threat_margin_factor * p.min_runner_up_margin >= best.n_matched
        if threat and k < p.max_runner_ups:
            res = _refine(inp.robot, inp.image, tree, h.image_from_robot, p)
            out.append(_refined(f"{name}, ICP-refined", res))
    return out


def _pose_text(t: F64, robot: F64) -> str:
    """The pose's rotation vector (degrees) and where it lands the robot centroid (mm)."""
    rotvec = np.degrees(Rotation.from_matrix(t[:3, :3]).as_rotvec())
    pos = t[:3, :3] @ robot.mean(axis=0) + t[:3, 3]
    return (
        f"rotation vector ({rotvec[0]:.1f}, {rotvec[1]:.1f}, {rotvec[2]:.1f})°, robot centroid at "
        f"({pos[0]:.1f}, {pos[1]:.1f}, {pos[2]:.1f}) mm"
    )


def check_runner_up(
    best: _Candidate, pool: Sequence[_Candidate], robot: F64, tree: cKDTree, p: RegistrationParams
) -> RunnerUp:
    """Step 5: the best pose must beat the best distinct runner-up by ``min_runner_up_margin``.

    Raises AmbiguousMatchError, or TooFewWithinGateError when there is no runner-up at all but the
    best pose itself has fewer than the margin's spheres within the fixed gate (a loose ICP fit).
    """
    ru = find_runner_up(best, pool, robot, tree, p)
    if ru.margin >= p.min_runner_up_margin:
        return ru
    if ru.candidate is None:
        raise TooFewWithinGateError(
            f"the best pose matched {best.n_matched} spheres by ICP but only {ru.n_best} lie within "
            f"{p.hypothesis_gate_mm:g} mm of a detection (a margin of {p.min_runner_up_margin} is "
            "required): the fit is loose. Check the detection and that the robot points belong to this scan"
        )
    raise AmbiguousMatchError(
        f"ambiguous sphere correspondence: the best pose matches {ru.n_best} spheres and a "
        f"different pose ({ru.candidate.source}, rotated {ru.rotation_deg:.1f}° from it: "
        f"{_pose_text(ru.candidate.image_from_robot, robot)}) matches "
        f"{ru.n_matched}; a margin of {p.min_runner_up_margin} is required. Give an orientation prior "
        "(--prior-rotation, tolerance < 45°), name 4 marks for the pre-registration, or use a phantom "
        "with an asymmetric filled pattern"
    )


@dataclass(frozen=True, eq=False)
class QualityFigures:
    """design.md §5 figures of the accepted pose."""

    conditioning: Conditioning
    rotation_det: float
    fre_mm: float
    fle_mm: float
    predicted_tre_mm: F64


def quality_figures(
    r: IcpResult, image_from_robot: F64, inp: RegistrationInputs, p: RegistrationParams
) -> QualityFigures:
    """Step 6: conditioning of the matched spheres, det R, FRE, FLE, predicted TRE; the FRE gate.

    Raises DegenerateConfigurationError, ImproperRotationError or AccuracyGateError.
    """
    matched = inp.robot[r.robot_indices]
    cond = check_configuration(
        matched,
        "matched spheres",
        min_collinear_ratio=p.min_collinear_ratio,
        min_coplanar_ratio=p.min_coplanar_ratio,
    )
    det = float(np.linalg.det(image_from_robot[:3, :3]))
    if not abs(det - 1.0) < DET_TOL:
        raise ImproperRotationError(
            f"det(R) = {det}: the registration produced a reflection or a scaled rotation, which the "
            "determinant fix must prevent; report this input as a bug"
        )
    fre = float(np.sqrt(np.mean(r.residuals_mm**2)))
    fle = fle_from_fre(fre, r.n_matched)
    tre = predicted_tre_mm(fle, matched, inp.targets) if len(inp.targets) else np.empty(0)
    if fre > p.max_fre_mm:
        raise AccuracyGateError(
            f"FRE {fre:.3f} mm over {r.n_matched} matched spheres exceeds the gate of {p.max_fre_mm:g} mm "
            f"(largest residual {float(np.max(r.residuals_mm)):.3f} mm at robot sphere "
            f"{int(r.robot_indices[int(np.argmax(r.residuals_mm))])}). Check that the robot did not move "
            "during the scan, the robot points' pose, and the detection"
        )
    return QualityFigures(cond, det, fre, fle, np.asarray(tre, dtype=np.float64))


def _result(
    inp: RegistrationInputs,
    cands: CandidatePool,
    best: _Candidate,
    r: IcpResult,
    ru: RunnerUp,
    q: QualityFigures,
    mirror_checked: bool,
    timings: dict[str, float],
) -> RegistrationResult:
    t_best = best.image_from_robot
    return RegistrationResult(
        image_from_robot=t_best,
        fre_mm=q.fre_mm,
        fle_mm=q.fle_mm,
        robot_indices=r.robot_indices,
        image_indices=r.image_indices,
        residuals_mm=r.residuals_mm,
        n_expected=inp.n,
        n_detected=inp.m,
        n_matched=r.n_matched,
        predicted_tre_mm=q.predicted_tre_mm,
        symmetry_margin=int(ru.margin),
        rotation_det=q.rotation_det,
        timings_s=timings,
        robot_mm=inp.robot,
        image_mm=inp.image,
        targets_robot_mm=inp.targets,
        runner_up_matched=int(ru.n_matched),
        runner_up_rotation_deg=ru.rotation_deg,
        runner_up_source=ru.candidate.source if ru.candidate else "",
        method="prereg+icp" if cands.prereg is not None else "triples+icp",
        n_icp_iterations=r.n_iterations,
        collinearity=q.conditioning.collinearity,
        planarity=q.conditioning.planarity,
        prior_angle_deg=None if cands.prior is None else rotation_difference_deg(t_best[:3, :3], cands.prior),
        prereg=cands.prereg,
        mirror_checked=mirror_checked,
        provenance={"software": f"oarmreg {__version__}"},
    )


def register_points(
    robot_mm: ArrayLike,
    image_mm: ArrayLike,
    *,
    params: RegistrationParams = RegistrationParams(),
    targets_robot_mm: ArrayLike | None = None,
    orientation_prior: ArrayLike | None = None,
    prior_tolerance_deg: float = 30.0,
    prereg_pairs: Sequence[tuple[int, int]] | None = None,
    phantom: Phantom | None = None,
) -> RegistrationResult:
    """Register labelled robot-space sphere centres to unlabelled image detections.

    Parameters
    ----------
    robot_mm : array_like, shape (N, 3)
        Sphere centres in the robot frame (mm), in the phantom's sphere order.
    image_mm : array_like, shape (M, 3)
        Detected centres in the image frame (DICOM LPS, mm), any order; some may
        be missing, some spurious.
    params : RegistrationParams
    targets_robot_mm : array_like, shape (T, 3), optional
        Points (robot frame, mm) where Fitzpatrick's TRE is predicted.
    orientation_prior : array_like, shape (3, 3) or (4, 4), optional
        Expected rotation of ``image_from_robot``; poses further than
        ``prior_tolerance_deg`` from it are discarded (resolves a symmetric phantom).
    prior_tolerance_deg : float
        Must be < 45°.
    prereg_pairs : sequence of 4 (robot_index, image_index), optional
        Four named marks for the paper's pre-registration (eq. 7); ICP starts
        from its rigid projection, and its rotation acts as the orientation
        prior unless one is given.
    phantom : Phantom, optional
        When given (and the robot points are this phantom's spheres), every
        symmetry twin of the best pose is refined and compared explicitly.

    Returns
    -------
    RegistrationResult

    Raises
    ------
    PointSetError
        Malformed input arrays.
    DegenerateConfigurationError
        Robot or matched spheres collinear / coplanar; coplanar marks.
    TooFewSpheresError
        Fewer than ``params.min_matched`` spheres matched.
    AmbiguousMatchError
        The best pose does not beat the best distinct runner-up by
        ``params.min_runner_up_margin`` matched spheres.
    MirroredInputError
        The detections match the robot points only as a mirror image.
    PriorMismatchError
        No pose within the prior's tolerance explains enough spheres.
    AccuracyGateError
        FRE above ``params.max_fre_mm``.
    """
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    inp = validate_inputs(
        robot_mm,
        image_mm,
        params,
        targets_robot_mm=targets_robot_mm,
        orientation_prior=orientation_prior,
        prior_tolerance_deg=prior_tolerance_deg,
        prereg_pairs=prereg_pairs,
    )
    tree = cKDTree(inp.image)
    cands = candidate_pool(inp, tree, params, phantom, timings)
    t0 = time.perf_counter()
    mirror_checked = check_mirror(inp, cands, tree, params)
    timings["mirror_check_s"] = time.perf_counter() - t0
    best, r = check_enough_matched(inp, cands, params)
    t0 = time.perf_counter()
    extra = exhaustive_candidates(best, cands.pool, inp, cands.prior, tree, params)
    timings["exhaustive_runner_up_s"] = time.perf_counter() - t0
    ru = check_runner_up(best, [*cands.pool, *extra], inp.robot, tree, params)
    t0 = time.perf_counter()
    q = quality_figures(r, best.image_from_robot, inp, params)
    timings["quality_s"] = time.perf_counter() - t0
    timings["total_s"] = time.perf_counter() - t_start
    log.info(
        "registered %d/%d spheres (%d detected): FRE %.3f mm, FLE %.3f mm, margin %d",
        r.n_matched,
        inp.n,
        inp.m,
        q.fre_mm,
        q.fle_mm,
        ru.margin,
    )
    return _result(inp, cands, best, r, ru, q, mirror_checked, timings)
