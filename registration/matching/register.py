"""From sphere centres to ``image_from_robot``: correspondence, ICP, symmetry and quality checks.

:func:`register_points` is the contract (brief "Registration"):

1. the robot configuration is checked (collinear / coplanar refused);
2. candidate poses come from the click-free triple search
   (:func:`registration.matching.correspondence.find_hypotheses`), or from the paper's
   four-mark pre-registration (eq. 7, :mod:`registration.matching.prereg`) when
   ``prereg_pairs`` are given;
3. an orientation prior, if any, discards poses rotated further than its
   tolerance (< 45°, half the 90° symmetry of the hole grid: research §1.6);
4. the best candidates and, when a :class:`~registration.model.phantom.Phantom` is
   given, every symmetry twin of the best pose are refined by gated ICP
   (:mod:`registration.matching.icp`); the best must explain at least
   ``min_runner_up_margin`` more spheres than the best *distinct* runner-up or
   the result is refused as ambiguous (design.md §4).  On a subset (at most
   ``exhaustive_runner_up_max_points`` detections) the runner-up comes from an
   exhaustive triple search
   (:func:`registration.matching.correspondence.exhaustive_runner_ups`), not only from
   the hypotheses that found the best pose;
5. the mirrored problem (image z → −z) is tried whenever it could explain
   clearly more spheres; if it does, the input is refused as mirrored;
6. with a phantom, its face offset β (one depth along every hole's axis, shared by the scan) is
   fitted with the pose (:mod:`registration.matching.face_offset`) and the scan refused when |β|
   is out of bounds;
7. quality figures (design.md §5) are computed and gated.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Sequence
from typing import Final

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from registration import __version__
from registration.arrays import F64
from registration.errors import (
    AccuracyGateError,
    ConfigError,
    ImproperRotationError,
    PhantomMismatchError,
    PointSetError,
    TooFewSpheresError,
)
from registration.matching.face_offset import FaceOffsetFit, check_face_offset, fit_face_offset
from registration.matching.hypotheses import (
    Candidate,
    CandidatePool,
    RunnerUp,
    candidate_pool,
    check_enough_matched,
    check_mirror,
    check_runner_up,
    exhaustive_candidates,
)
from registration.matching.icp import IcpResult
from registration.matching.quality import (
    check_configuration,
    fle_from_fre,
    predicted_tre_mm,
)
from registration.matching.records import (
    MAX_PRIOR_TOLERANCE_DEG,
    QualityFigures,
    RegistrationInputs,
    RegistrationParams,
    RegistrationResult,
    as_rotation,
)
from registration.matching.rigid import as_points, fit_rigid_unchecked, rotation_difference_deg
from registration.model.phantom import Phantom

log = logging.getLogger(__name__)

I64 = NDArray[np.int64]


DET_TOL: Final = 1e-9
"""det R of the result must be 1 within this: Kabsch with the determinant fix gives 1 to rounding."""


# ----------------------------------------------------------------------------- the steps
# register_points runs these in order; each refuses with its own typed error.


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
    robot = as_points(robot_mm, "robot points")
    image = as_points(image_mm, "image points")
    n, m = len(robot), len(image)
    targets = (
        np.empty((0, 3))
        if targets_robot_mm is None
        else as_points(np.reshape(targets_robot_mm, (-1, 3)), "targets")
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
    prior = None if orientation_prior is None else as_rotation(orientation_prior)
    if not 0.0 < prior_tolerance_deg < MAX_PRIOR_TOLERANCE_DEG:
        raise ConfigError(
            f"orientation prior tolerance must be in (0, {MAX_PRIOR_TOLERANCE_DEG:g})°, got "
            f"{prior_tolerance_deg:g}°: the hole grid repeats every 90°"
        )
    pairs = None if prereg_pairs is None else _prereg_pairs(prereg_pairs, n, m)
    return RegistrationInputs(robot, image, targets, prior, float(prior_tolerance_deg), pairs)


def check_phantom_fit(n_expected: int, n_detected: int, n_matched: int, p: RegistrationParams) -> None:
    """Step 5b: does the scan look like the phantom file?  Far more detections than its spheres, or
    a best pose that explains a small share of them, suggests another phantom.

    Raises PhantomMismatchError unless ``p.phantom_confirmed`` (then it only warns).
    """
    unexplained = n_detected - n_matched
    problem = ""
    if n_detected > p.max_detected_per_expected * n_expected:
        problem = (
            f"{n_detected} spheres detected but the phantom file has {n_expected} "
            f"(more than {p.max_detected_per_expected:g} ×)"
        )
    elif unexplained >= p.min_unexplained_for_mismatch and n_matched < p.min_matched_share * n_detected:
        problem = (
            f"the best pose matches only {n_matched} of {n_detected} detected spheres "
            f"({n_matched / n_detected:.0%}, below {p.min_matched_share:.0%}; "
            f"the phantom file has {n_expected})"
        )
    if not problem:
        return
    if p.phantom_confirmed:
        log.warning("%s; registering anyway: the phantom file was confirmed", problem)
        return
    raise PhantomMismatchError(
        f"{problem}: check the phantom file (is it the phantom on the rod?). If it is, register again "
        "confirming it (`oarmreg register --phantom-confirmed`, or POST /register with "
        '"phantom_confirmed": true)'
    )


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
            f"{int(r.robot_indices[int(np.argmax(r.residuals_mm))])}). Likely causes: the phantom file "
            "does not describe the phantom scanned (check its pitch and sphere positions), the robot "
            "moved during the scan, the robot points' pose (joints, rod), or the detection"
        )
    return QualityFigures(cond, det, fre, fle, np.asarray(tre, dtype=np.float64))


def face_offset_step(
    inp: RegistrationInputs, r: IcpResult, phantom: Phantom | None, p: RegistrationParams
) -> FaceOffsetFit | None:
    """Step 5b: the phantom's face offset β fitted with the pose over the matched pairs.

    The robot points are the phantom's spheres in its order, so ``robot_from_phantom``'s rotation
    (a Kabsch fit of the phantom's centres to them) carries each hole's axis into the robot frame.
    None without a phantom, with the fit turned off, or when the robot points are not the
    phantom's spheres.  Raises FaceOffsetError when |β| exceeds ``p.max_face_offset_mm``.
    """
    if phantom is None or not p.face_offset_fit or inp.n != phantom.n_spheres:
        return None
    robot_from_phantom = fit_rigid_unchecked(phantom.centres_phantom_mm, inp.robot)
    axes_robot = phantom.axes_phantom @ robot_from_phantom[:3, :3].T
    fit = fit_face_offset(inp.robot[r.robot_indices], axes_robot[r.robot_indices], inp.image[r.image_indices])
    ids = phantom.filled_ids
    check_face_offset(fit, tuple(ids[int(i)] for i in r.robot_indices), p.max_face_offset_mm)
    return fit


def _result(
    inp: RegistrationInputs,
    cands: CandidatePool,
    best: Candidate,
    r: IcpResult,
    ru: RunnerUp,
    q: QualityFigures,
    mirror_checked: bool,
    timings: dict[str, float],
    face: FaceOffsetFit | None = None,
) -> RegistrationResult:
    t_best = best.image_from_robot
    return RegistrationResult(
        face_offset_mm=None if face is None else face.beta_mm,
        face_offset_se_mm=None if face is None or math.isnan(face.beta_se_mm) else face.beta_se_mm,
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
    check_phantom_fit(inp.n, inp.m, r.n_matched, params)
    t0 = time.perf_counter()
    face = face_offset_step(inp, r, phantom, params)
    if face is not None:  # the pose and residuals of the 7-parameter fit, β·n_i removed
        r = dataclasses.replace(r, image_from_robot=face.image_from_model, residuals_mm=face.residuals_mm)
        best = dataclasses.replace(best, image_from_robot=face.image_from_model, result=r)
    timings["face_offset_s"] = time.perf_counter() - t0
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
    return _result(inp, cands, best, r, ru, q, mirror_checked, timings, face)
