"""Partial imaging (issue #11 item 3): a scan showing a subset of ≥ 6 of the phantom's spheres.

The robot side lists every filled sphere of ``bai2018_cube`` (28, on a 15 mm grid, so subsets of
one face are often ambiguous); the image shows a drawn subset (a half-space cut, like a phantom
partly outside the field of view, then random drops) at a drawn pose, in random order, with
0.03 mm noise.  An independent brute-force oracle enumerates every pose that maps *some* robot
triple onto *some* image triple of matching side lengths and counts the robot spheres it lands
within the hypothesis gate of a detection; the subset's margin is the truth's count minus the
best count of a pose distinct from the truth.

Contract: never a wrong match; answered (correctly) when the margin clears the setting with one
sphere to spare for ICP (which may add a sphere to a runner-up's count); refused when the margin
is below the setting.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, event, given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from registration.errors import RegistrationError
from registration.matching.records import (
    RegistrationParams,
)
from registration.matching.register import (
    register_points,
)
from registration.matching.rigid import fit_rigid_batch, rotation_difference_deg
from registration.model.phantom import load_phantom

F64 = NDArray[np.float64]
P = RegistrationParams()
NOISE_MM = 0.03
"""Per-axis detection noise: the measured FLE of the steel presets is 0.04–0.06 mm (mean error)."""
ORACLE_TOL_MM = 0.3
"""Side lengths agree in the oracle within this (10 σ of a noisy distance, ≪ the 15 mm pitch)."""


@pytest.fixture(scope="module")
def cube():  # type: ignore[no-untyped-def]
    from tests.helpers.paths import CONFIGS

    return load_phantom(CONFIGS / "phantoms" / "bai2018_cube.toml")


def _distinct(t: F64, truth: F64, centroid: F64) -> bool:
    if rotation_difference_deg(t[:3, :3], truth[:3, :3]) > P.distinct_rotation_deg:
        return True
    d = (t[:3, :3] - truth[:3, :3]) @ centroid + t[:3, 3] - truth[:3, 3]
    return bool(np.linalg.norm(d) > P.distinct_translation_mm)


def oracle_runner_up(robot: F64, image: F64, truth: F64) -> int:
    """Most robot spheres any pose distinct from ``truth`` lands within the gate of a detection."""
    n = len(robot)
    d_r = np.linalg.norm(robot[:, None] - robot[None], axis=2)
    abc = np.array([t for t in itertools.permutations(range(n), 3)])
    best = 0
    centroid = robot.mean(axis=0)
    for i, j, k in itertools.combinations(range(len(image)), 3):
        dij, dik, djk = (float(np.linalg.norm(image[x] - image[y])) for x, y in ((i, j), (i, k), (j, k)))
        ok = (
            (np.abs(d_r[abc[:, 0], abc[:, 1]] - dij) < ORACLE_TOL_MM)
            & (np.abs(d_r[abc[:, 0], abc[:, 2]] - dik) < ORACLE_TOL_MM)
            & (np.abs(d_r[abc[:, 1], abc[:, 2]] - djk) < ORACLE_TOL_MM)
        )
        if not ok.any():
            continue
        ts = fit_rigid_batch(robot[abc[ok]], np.broadcast_to(image[[i, j, k]], (int(ok.sum()), 3, 3)))
        mapped = np.einsum("hij,pj->hpi", ts[:, :3, :3], robot) + ts[:, None, :3, 3]
        dist = np.linalg.norm(mapped[:, :, None] - image[None, None], axis=3).min(axis=2)
        counts = (dist < P.hypothesis_gate_mm).sum(axis=1)
        for t, c in zip(ts, counts, strict=True):
            if c > best and _distinct(t, truth, centroid):
                best = int(c)
    return best


N_SPHERES = 28
"""Filled spheres of ``bai2018_cube`` (the strategy draws one drop value per sphere)."""


def _unit(draw: st.DrawFn, k: int) -> F64:
    """A unit vector of ``k`` components drawn as floats (shrinks towards the last axis: for a
    quaternion (x, y, z, w), the identity rotation)."""
    v = np.array(draw(st.lists(st.floats(-1.0, 1.0), min_size=k, max_size=k)), dtype=np.float64)
    norm = float(np.linalg.norm(v))
    if norm < 1e-3:
        v, norm = np.eye(k)[k - 1], 1.0
    return v / norm


@st.composite
def partial_scans(draw: st.DrawFn) -> tuple[F64, F64, float, F64, int]:
    """(image_from_robot, cut normal, half-space cut offset mm, per-sphere keep draws, noise seed).

    Rotation (a unit quaternion from 4 floats), translation, cut normal and which spheres are dropped
    are all drawn by hypothesis, so a failure shrinks; only the noise and the detection order come
    from a seeded generator.
    """
    t = np.eye(4)
    t[:3, :3] = Rotation.from_quat(_unit(draw, 4)).as_matrix()
    t[:3, 3] = draw(st.lists(st.floats(-50.0, 50.0), min_size=3, max_size=3))
    normal = _unit(draw, 3)
    cut_mm = draw(st.floats(min_value=-35.0, max_value=25.0))
    drop = draw(st.floats(min_value=0.0, max_value=0.4))
    u = np.array(draw(st.lists(st.floats(0.0, 1.0), min_size=N_SPHERES, max_size=N_SPHERES)))
    seed = draw(st.integers(0, 2**31 - 1))
    return t, normal, cut_mm, u >= drop, seed


@settings(
    max_examples=60,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
    derandomize=True,  # the same 60 draws every run: the counterexample below was found by a random run
)
@given(scan=partial_scans())
def test_partial_subset_answered_or_refused_never_wrong(cube, scan) -> None:  # type: ignore[no-untyped-def]
    check_partial_subset(cube, *scan)


def test_known_counterexample_runner_up_missed(cube) -> None:  # type: ignore[no-untyped-def]
    """Found by a random run: an 8-sphere half-cube subset where a distinct pose explains 6 spheres
    (margin 2).  The exhaustive runner-up search binned poses before counting them and kept a
    5-sphere pose of the bin, answering with margin 3; it now keeps each bin's best."""
    flip = np.diag([-1.0, 1.0, -1.0, 1.0])
    kept = np.zeros(N_SPHERES, dtype=bool)
    kept[[4, 10, 11, 13, 15, 17, 19, 27]] = True
    check_partial_subset(cube, flip, np.array([0.0, 0.0, 1.0]), 0.0, kept, 0)


def check_partial_subset(  # type: ignore[no-untyped-def]
    cube, image_from_robot: F64, normal: F64, cut_mm: float, kept: NDArray[np.bool_], seed: int
) -> None:
    """Register the spheres kept on one side of a cut: refused, or right with an honest margin."""
    from hypothesis.control import currently_in_test_context

    note = event if currently_in_test_context() else (lambda _: None)
    rng = np.random.default_rng(seed)
    robot = cube.centres_phantom_mm
    assert len(robot) == N_SPHERES
    keep = np.flatnonzero((robot @ normal > cut_mm) & kept)
    if currently_in_test_context():
        assume(len(keep) >= P.min_matched)
    else:  # a fixed example: its subset must be big enough, else it tests nothing
        assert len(keep) >= P.min_matched
    order = rng.permutation(keep)
    image = robot[order] @ image_from_robot[:3, :3].T + image_from_robot[:3, 3]
    image = image + rng.normal(scale=NOISE_MM, size=image.shape)
    margin = len(keep) - oracle_runner_up(robot, image, image_from_robot)
    try:
        r = register_points(robot, image, phantom=cube)
    except RegistrationError as e:
        note(f"refused, margin {'< setting' if margin < P.min_runner_up_margin else '>= setting'}")
        assert margin < P.min_runner_up_margin + 1, f"refused an unambiguous subset (margin {margin}): {e}"
        return
    note("answered")
    assert np.array_equal(order[r.image_indices], r.robot_indices), "wrong match"
    assert r.n_matched == len(keep)
    assert margin >= P.min_runner_up_margin, f"answered an ambiguous subset (oracle margin {margin})"
    if len(keep) <= P.exhaustive_runner_up_max_points:
        # the exhaustive search saw every pose the oracle saw (its side tolerance is looser)
        assert r.runner_up_matched >= len(keep) - margin, "runner-up weaker than the oracle's"
