"""Candidate poses for the registration, and the checks that choose among them.

Hypotheses from the triple search or the four-mark pre-registration, the phantom's symmetry twins
of the best pose, gated ICP on each (:mod:`registration.matching.icp`); then the mirrored check,
the enough-matched check and the runner-up margin that refuses an ambiguous match (design.md §4).
:func:`registration.matching.register.register_points` runs them in order."""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from registration.arrays import F64
from registration.errors import (
    AmbiguousMatchError,
    MirroredInputError,
    PriorMismatchError,
    TooFewSpheresError,
    TooFewWithinGateError,
)
from registration.matching.correspondence import (
    Hypothesis,
    exhaustive_runner_ups,
    find_hypotheses,
    same_pose,
)
from registration.matching.icp import IcpResult, icp
from registration.matching.prereg import PreregResult, preregister
from registration.matching.records import RegistrationInputs, RegistrationParams
from registration.matching.rigid import fit_rigid, rotation_difference_deg
from registration.model.phantom import Phantom

log = logging.getLogger(__name__)


I64 = NDArray[np.int64]


PHANTOM_FIT_MAX_RMS_MM: Final = 1.0
"""The robot points must match the phantom's CAD centres within this RMS (mm) for the phantom's
symmetry twins to be tried; otherwise the robot points are not this phantom's."""


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
class Candidate:
    """A pose in the competition: refined by ICP, or only counted (cannot threaten the best)."""

    source: str
    image_from_robot: F64
    n_matched: int
    rms_mm: float
    result: IcpResult | None = None


def _key(c: Candidate) -> tuple[int, float]:
    return (c.n_matched, -c.rms_mm)


def _refined(source: str, res: IcpResult) -> Candidate:
    return Candidate(source, res.image_from_robot, res.n_matched, res.rms_mm, res)


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


@dataclass
class CandidatePool:
    """Every pose that competed, and the best of them (None if no consistent triple exists)."""

    best: Candidate | None
    pool: list[Candidate]
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
    best: Candidate,
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
    best: Candidate,
    others: list[tuple[str, F64, int, float]],
    inp: RegistrationInputs,
    tree: cKDTree,
    p: RegistrationParams,
    *,
    best_is_fixed: bool,
) -> tuple[Candidate, list[Candidate]]:
    """Refine the poses that threaten ``best`` by ICP, count the rest; return (best, the competitors).

    A pose is refined only if it comes within ``threat_margin_factor × min_runner_up_margin`` of the
    best (at most ``max_runner_ups + max_refined_twins`` of them).  ``best_is_fixed``: the named
    pre-registration marks define the pose, the others only compete as runner-ups.
    """
    pool: list[Candidate] = []
    n_refined = 0
    for name, t_o, n_o, rms_o in others:
        threat = n_o + p.threat_margin_factor * p.min_runner_up_margin >= best.n_matched
        if threat and n_refined < p.max_runner_ups + p.max_refined_twins:
            n_refined += 1
            cand = _refined(name, _refine(inp.robot, inp.image, tree, t_o, p))
        else:
            cand = Candidate(name, t_o, n_o, rms_o)
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
    pool: list[Candidate] = []
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
    best: Candidate | None = None
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
) -> tuple[Candidate, IcpResult]:
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
    candidate: Candidate | None
    n_matched: int
    rotation_deg: float | None

    @property
    def margin(self) -> int:
        return self.n_best - self.n_matched


def find_runner_up(
    best: Candidate, pool: Sequence[Candidate], robot: F64, tree: cKDTree, p: RegistrationParams
) -> RunnerUp:
    """The best pose of ``pool`` that is distinct from ``best`` (same_pose), by count at the fixed gate.

    Every pose is counted at the same fixed gate: ICP's gate adapts to each pose's own residuals,
    so a wrong pose refined by ICP would be flattered by its loose matches.
    """
    t_best = best.image_from_robot
    n_best = _quick_count(t_best, robot, tree, p.hypothesis_gate_mm)[0]
    centroid = robot.mean(axis=0)
    runner: Candidate | None = None
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
    best: Candidate,
    pool: Sequence[Candidate],
    inp: RegistrationInputs,
    prior: F64 | None,
    tree: cKDTree,
    p: RegistrationParams,
) -> list[Candidate]:
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
    out: list[Candidate] = []
    for k, h in enumerate(hyps):
        name = f"exhaustive search pose {k}"
        out.append(Candidate(name, h.image_from_robot, h.n_inliers, h.rms_mm))
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
    best: Candidate, pool: Sequence[Candidate], robot: F64, tree: cKDTree, p: RegistrationParams
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
