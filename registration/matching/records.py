"""The registration step's records: its settings, its checked inputs and its result, and the errors of
malformed point sets and priors (:func:`registration.matching.register.register_points` uses them)."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any, Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.arrays import F64
from registration.errors import (
    ConfigError,
)
from registration.matching.correspondence import (
    DEFAULT_DISTINCT_ROTATION_DEG,
    DEFAULT_DISTINCT_TRANSLATION_MM,
)
from registration.matching.face_offset import MAX_FACE_OFFSET_MM
from registration.matching.prereg import PreregResult
from registration.matching.quality import (
    Conditioning,
)

log = logging.getLogger(__name__)


I64 = NDArray[np.int64]


MAX_PRIOR_TOLERANCE_DEG: Final = 45.0
"""An orientation prior must be tighter than half the 90° grid symmetry to separate twins."""


PRIOR_ROTATION_TOL: Final = 1e-3
"""An orientation prior is a rotation if RᵀR = I and det R = 1 within this: a matrix written with 4
decimals (a hand-typed prior) passes, a scaled or sheared one does not."""


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
    their runner-up from :func:`registration.matching.correspondence.exhaustive_runner_ups`: every image
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
    """λ2/λ1 below this = collinear spheres (see registration.matching.quality)."""
    min_coplanar_ratio: float = 1e-3
    """λ3/λ1 below this = coplanar spheres (see registration.matching.quality)."""
    mirror_axis: int = 2
    """Image axis negated to build the mirrored problem (2 = z, the slice axis most often flipped)."""
    mirror_min_fraction: float = 0.75
    """The mirrored problem must explain this fraction of min(expected, detected) spheres to call the
    input mirrored: the cube grid is achiral, so a mirror image of a filled pattern still overlaps
    the proper pattern partly (14 of 28 spheres for bai2018_cube) and must not win by default."""
    max_detected_per_expected: float = 1.25
    """More detections than this × the phantom's spheres and the scan probably holds another
    phantom (a 40-sphere phantom read with a 28-sphere file: 40 > 35).  A clean scan detects at most
    the phantom's spheres plus a few rejected-late blobs."""
    min_matched_share: float = 0.7
    """The best pose must explain this share of the detections (when at least
    ``min_unexplained_for_mismatch`` are left over): 18 of 40 (0.45) is a wrong phantom file; a
    subset scan (8 of 28 in the field) explains nearly all of its own detections."""
    min_unexplained_for_mismatch: int = 4
    """Leftover detections below this never call the phantom file into question (a screw, a blob)."""
    phantom_confirmed: bool = False
    """The user confirmed the phantom file: the two checks above warn in the log instead of refusing."""
    face_offset_fit: bool = True
    """Fit the phantom's face offset β with the pose when a phantom is given
    (:mod:`registration.matching.face_offset`): the matched centres are taken with β·n_i removed."""
    max_face_offset_mm: float = MAX_FACE_OFFSET_MM
    """Largest |β| accepted (origin: :data:`registration.matching.face_offset.MAX_FACE_OFFSET_MM`)."""
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
    face_offset_mm: float | None = None
    """The phantom's face offset β of this scan, mm (None when not fitted: no phantom given)."""
    face_offset_se_mm: float | None = None
    """β's standard error, mm (None when not fitted or undetermined)."""

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
            "face_offset_mm": self.face_offset_mm,
            "face_offset_se_mm": self.face_offset_se_mm,
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


def as_rotation(prior: ArrayLike) -> F64:
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


@dataclass(frozen=True, eq=False)
class QualityFigures:
    """design.md §5 figures of the accepted pose."""

    conditioning: Conditioning
    rotation_det: float
    fre_mm: float
    fle_mm: float
    predicted_tre_mm: F64
