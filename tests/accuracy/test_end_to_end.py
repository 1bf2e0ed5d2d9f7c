"""End-to-end accuracy from simulated O-arm DICOM (issue #4 "Done when", CI-sized).

Two scans at O-arm pixel size (0.415 / 0.424 mm) on a reduced 256 × 256 matrix (106–109 mm field,
the phantom centred so all 28 spheres are inside), posed by TX60 forward kinematics and a hidden
``image_from_robot``; written as DICOM (reversed file order / unsigned pixels), loaded, detected,
registered against the kinematic centres + σ = 0.02 mm robot noise.  The TRUE TRE at 14 targets
150 mm from the phantom centre is checked: ≤ 0.15 mm per case, ≤ 0.10 mm mean.  The full-size
figures are in ``benchmarks/bench_end_to_end.py``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from mocks.oarm.dicom_export import write_dicom_series
from mocks.oarm.simulator import (
    AcquisitionSettings,
    SceneExtras,
    SimulatedScan,
    image_from_scanner,
    simulate_scan,
)
from registration.detection import detect_spheres, params_for_spheres
from registration.dicom import load_series
from registration.matching.records import (
    RegistrationResult,
)
from registration.matching.register import (
    register_points,
)
from registration.model import frames
from registration.model.kinematics import RobotModel, default_tool0_from_phantom, sphere_centres_robot_mm

F64 = NDArray[np.float64]
TARGET_DISTANCE_MM = 150.0
ROBOT_SIGMA_MM = 0.02
MAX_CASE_TRE_MM = 0.15
MAX_MEAN_TRE_MM = 0.10
"""Issue #4: mean TRE at 150 mm ≤ 0.10 mm end to end; 0.15 mm per case leaves room for one unlucky scan."""
MAX_TRE_OVER_PREDICTED = 3.0
"""Per-case measured RMS TRE over Fitzpatrick's prediction: the benchmark's 1.5 is a mean over many
scans; one scan's ratio scatters (TRE² is ≈ χ² with few degrees of freedom), hence 3 here."""
MATCH_TRUTH_MM = 1.25


@dataclass(frozen=True)
class Case:
    name: str
    joints_rad: tuple[float, ...]
    spin_deg: float
    tilt_deg: float
    tilt_axis_deg: float
    offset_mm: tuple[float, float, float]
    pixel_mm: float
    slice_spacing_mm: float
    orientation: str
    rod: bool
    reverse_order: bool
    unsigned: bool
    seed: int


CASES = (
    Case(
        name="axial-0.415x0.833-reversed",
        joints_rad=(0.2, -0.15, 1.75, 0.3, 0.6, -0.9),
        spin_deg=37.0,
        tilt_deg=12.0,
        tilt_axis_deg=60.0,
        offset_mm=(1.5, -1.0, 2.0),
        pixel_mm=0.415,
        slice_spacing_mm=0.833,
        orientation="axial",
        rod=False,
        reverse_order=True,
        unsigned=False,
        seed=11,
    ),
    Case(
        name="flipped-0.424x0.625-unsigned-rod",
        joints_rad=(-0.3, 0.2, 1.4, -0.4, 0.95, 1.2),
        spin_deg=203.0,
        tilt_deg=18.0,
        tilt_axis_deg=-100.0,
        offset_mm=(-1.0, 2.0, -1.5),
        pixel_mm=0.424,
        slice_spacing_mm=0.625,
        orientation="axial-flipped",
        rod=True,
        reverse_order=False,
        unsigned=True,
        seed=12,
    ),
)
AXIAL_COVERAGE_MM = 110.0
"""Covers the phantom's spheres (≤ 47.7 mm from its centre) at these tilts and offsets."""


def _target_directions() -> F64:
    diag = np.array(np.meshgrid([-1.0, 1.0], [-1.0, 1.0], [-1.0, 1.0])).reshape(3, -1).T / math.sqrt(3.0)
    return np.asarray(np.vstack([np.eye(3), -np.eye(3), diag]), dtype=np.float64)


@dataclass
class Outcome:
    case: Case
    scan: SimulatedScan
    detections_image_mm: F64
    truth_labels: NDArray[np.int64]  # phantom sphere index of each detection, -1 = none within a radius
    result: RegistrationResult
    hidden_image_from_robot: F64
    tre_mm: F64  # (14,) true TRE at the targets


def _run(case: Case, phantom: Any, model: RobotModel, out: Path) -> Outcome:
    rod = default_tool0_from_phantom()
    robot_from_phantom = model.robot_from_tool0(case.joints_rad) @ rod
    a = math.radians(case.tilt_axis_deg)
    rot = Rotation.from_rotvec(math.radians(case.tilt_deg) * np.array([math.cos(a), math.sin(a), 0.0]))
    rot = rot * Rotation.from_euler("z", case.spin_deg, degrees=True)
    image_from_phantom = image_from_scanner(case.orientation) @ frames.make_transform(
        rot.as_matrix(), case.offset_mm
    )
    hidden = image_from_phantom @ frames.invert(robot_from_phantom)
    settings = AcquisitionSettings.preset(
        "demo",
        rows=256,
        columns=256,
        pixel_mm=case.pixel_mm,
        slice_spacing_mm=case.slice_spacing_mm,
        n_slices=math.ceil(AXIAL_COVERAGE_MM / case.slice_spacing_mm),
        orientation=case.orientation,
        seed=case.seed,
    )
    scan = simulate_scan(phantom, image_from_phantom, settings, SceneExtras(rod=case.rod))
    write_dicom_series(scan, out, reverse_order=case.reverse_order, unsigned=case.unsigned)
    det = detect_spheres(
        load_series(out), params_for_spheres(phantom.sphere_material, phantom.sphere_diameter_mm)
    ).centres_image_mm
    labels = np.full(len(det), -1, dtype=np.int64)
    if len(det):
        dist, nearest = cKDTree(scan.spheres_image_mm).query(det)
        labels[dist <= MATCH_TRUTH_MM] = scan.sphere_indices[nearest[dist <= MATCH_TRUTH_MM]]
    rng = np.random.default_rng(case.seed)
    robot_mm = sphere_centres_robot_mm(model, case.joints_rad, rod, phantom.centres_phantom_mm)
    robot_mm = robot_mm + rng.normal(0.0, ROBOT_SIGMA_MM, robot_mm.shape)
    targets = robot_from_phantom[:3, 3] + TARGET_DISTANCE_MM * _target_directions()
    result = register_points(robot_mm, det, targets_robot_mm=targets, phantom=phantom)
    tre = np.linalg.norm(
        frames.apply(result.image_from_robot, targets) - frames.apply(hidden, targets), axis=1
    )
    return Outcome(case, scan, det, labels, result, hidden, tre)


@pytest.fixture(scope="module")
def outcomes(phantom: Any, tmp_path_factory: pytest.TempPathFactory) -> list[Outcome]:
    model = RobotModel.load("tx60")
    return [_run(c, phantom, model, tmp_path_factory.mktemp(c.name)) for c in CASES]


@pytest.mark.parametrize("i", range(len(CASES)), ids=[c.name for c in CASES])
def test_every_sphere_is_in_the_reduced_volume(outcomes: list[Outcome], phantom: Any, i: int) -> None:
    scan = outcomes[i].scan
    assert scan.sphere_indices.tolist() == list(range(phantom.n_spheres)) == list(range(28))


@pytest.mark.parametrize("i", range(len(CASES)), ids=[c.name for c in CASES])
def test_correspondence_is_the_truth(outcomes: list[Outcome], i: int) -> None:
    o = outcomes[i]
    res = o.result
    matched_truth = o.truth_labels[res.image_indices]
    assert (matched_truth >= 0).all(), "a matched detection is not a real sphere"
    np.testing.assert_array_equal(matched_truth, res.robot_indices)
    assert res.n_matched >= 26, f"only {res.n_matched}/28 spheres matched"


@pytest.mark.parametrize("i", range(len(CASES)), ids=[c.name for c in CASES])
def test_true_tre_at_150_mm_per_case(outcomes: list[Outcome], i: int) -> None:
    o = outcomes[i]
    assert o.tre_mm.shape == (14,)
    assert float(o.tre_mm.max()) <= MAX_CASE_TRE_MM, o.tre_mm
    # the reported quality figures are honest for this scan
    predicted_rms = float(np.sqrt(np.mean(o.result.predicted_tre_mm**2)))
    measured_rms = float(np.sqrt(np.mean(o.tre_mm**2)))
    assert predicted_rms <= MAX_CASE_TRE_MM
    assert measured_rms <= MAX_TRE_OVER_PREDICTED * predicted_rms, (measured_rms, predicted_rms)


def test_mean_tre_at_150_mm_over_cases(outcomes: list[Outcome]) -> None:
    mean_tre = float(np.mean([o.tre_mm.mean() for o in outcomes]))
    assert mean_tre <= MAX_MEAN_TRE_MM, mean_tre
