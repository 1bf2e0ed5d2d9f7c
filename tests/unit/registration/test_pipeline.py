"""registration/pipeline.py on one small simulated scan with a known ``image_from_robot``.

The pipeline is called directly: no service, database, watcher or robot link.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
from numpy.typing import NDArray

from registration.errors import RegistrationError
from registration.imaging.volume import Volume
from registration.model.frames import apply, invert, transform_from_xyz_rpy
from registration.model.kinematics import RobotModel
from registration.model.phantom import Phantom
from registration.pipeline import (
    PipelineParams,
    default_targets_robot_mm,
    register_scan,
    verify_scan,
)
from tests.helpers.scan_cache import simulated_scan

Q = (0.0, 0.0, np.pi / 2, 0.0, np.pi / 4, 0.0)
TOOL0_FROM_PHANTOM = transform_from_xyz_rpy([0, 0, 200], [180, 0, 0])
TRE_LIMIT_MM = 0.15
"""True error at 150 mm from the phantom centre (the service loop's acceptance figure)."""


@dataclass(frozen=True)
class Case:
    phantom: Phantom
    model: RobotModel
    volume: Volume
    image_from_robot: NDArray[np.float64]


@pytest.fixture(scope="module")
def case(phantom: Phantom) -> Case:
    from mocks.oarm.simulator import AcquisitionSettings, scan_to_volume

    model = RobotModel.load("tx60")
    image_from_phantom = transform_from_xyz_rpy([2.0, -3.0, 1.0], [10.0, -6.0, 20.0])
    image_from_robot = image_from_phantom @ invert(model.robot_from_tool0(Q) @ TOOL0_FROM_PHANTOM)
    scan = simulated_scan(phantom, image_from_phantom, AcquisitionSettings.preset("small"))
    return Case(phantom, model, scan_to_volume(scan), image_from_robot)


def test_register_scan_recovers_image_from_robot(case: Case) -> None:
    out = register_scan(case.volume, Q, case.model, TOOL0_FROM_PHANTOM, case.phantom)
    centre = (case.model.robot_from_tool0(Q) @ TOOL0_FROM_PHANTOM)[:3, 3]
    np.testing.assert_allclose(out.spheres.centre_robot_mm, centre, atol=1e-9)
    pts = default_targets_robot_mm(centre, 150.0)
    err = np.linalg.norm(apply(out.result.image_from_robot, pts) - apply(case.image_from_robot, pts), axis=1)
    assert float(err.max()) <= TRE_LIMIT_MM
    assert out.result.n_matched >= 20 and out.result.n_expected == len(case.phantom.filled_ids)
    assert len(out.spheres.image_mm) == out.result.n_detected
    assert set(out.timings_s) == {"detect_s", "register_s"}


def test_default_targets_are_reported_in_the_image_frame(case: Case) -> None:
    out = register_scan(case.volume, Q, case.model, TOOL0_FROM_PHANTOM, case.phantom)
    assert not out.targets_given and out.targets_image_mm.shape == (6, 3)
    expected = apply(
        out.result.image_from_robot, default_targets_robot_mm(out.spheres.centre_robot_mm, 150.0)
    )
    np.testing.assert_allclose(out.targets_image_mm, expected, atol=1e-9)
    np.testing.assert_allclose(out.predicted_tre_mm, out.result.predicted_tre_mm, rtol=0, atol=0)
    assert np.all((out.predicted_tre_mm > 0) & (out.predicted_tre_mm < 1))


def test_image_frame_targets_are_mapped_back_before_the_tre_formula(case: Case) -> None:
    """The default targets, given back in the image frame, must give the same predicted TRE."""
    default = register_scan(case.volume, Q, case.model, TOOL0_FROM_PHANTOM, case.phantom)
    given = register_scan(
        case.volume,
        Q,
        case.model,
        TOOL0_FROM_PHANTOM,
        case.phantom,
        targets_image_mm=default.targets_image_mm,
    )
    assert given.targets_given
    np.testing.assert_allclose(given.targets_image_mm, default.targets_image_mm, rtol=0, atol=0)
    np.testing.assert_allclose(given.predicted_tre_mm, default.predicted_tre_mm, rtol=1e-9)
    far = register_scan(
        case.volume,
        Q,
        case.model,
        TOOL0_FROM_PHANTOM,
        case.phantom,
        targets_image_mm=[[0.0, 0.0, 0.0], [0, 0, 400]],
    )
    assert far.predicted_tre_mm.shape == (2,) and far.predicted_tre_mm[1] > far.predicted_tre_mm[0]


def test_verify_scan_of_the_same_pose_has_small_errors(case: Case) -> None:
    spheres, res = verify_scan(
        case.volume, Q, case.model, TOOL0_FROM_PHANTOM, case.phantom, case.image_from_robot
    )
    assert res.n_matched >= 20 and res.max_mm < 0.5 and len(spheres.robot_mm) == len(case.phantom.filled_ids)


def test_a_scan_without_spheres_is_refused(case: Case) -> None:
    empty = Volume(np.full((24, 32, 32), -1000, dtype=np.int16), case.volume.image_from_voxel)
    with pytest.raises(RegistrationError):
        register_scan(empty, Q, case.model, TOOL0_FROM_PHANTOM, case.phantom)


def test_the_params_gates_apply(case: Case) -> None:
    from registration.matching.records import (
        RegistrationParams,
    )

    strict = PipelineParams(registration=RegistrationParams(max_fre_mm=1e-4))
    with pytest.raises(RegistrationError, match="FRE"):
        register_scan(case.volume, Q, case.model, TOOL0_FROM_PHANTOM, case.phantom, strict)
