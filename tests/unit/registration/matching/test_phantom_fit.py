"""A scan that does not look like the phantom file is refused with "check the phantom file" unless
the user confirms it (issue 42, item 4)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from registration.errors import AccuracyGateError, PhantomMismatchError
from registration.io.resources import default_phantom
from registration.matching.records import RegistrationParams
from registration.matching.register import check_phantom_fit, register_points
from registration.model.frames import transform_from_xyz_rpy
from registration.model.phantom import load_phantom

P = RegistrationParams()


def _scene() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The default phantom's spheres (robot frame), their image, and 12 extra spheres one pitch
    beyond its grid (as a 40-sphere phantom read with the 28-sphere file shows them)."""
    robot = load_phantom(default_phantom()).centres_phantom_mm
    image_from_robot = transform_from_xyz_rpy([5.0, -20.0, 140.0], [10.0, -5.0, 30.0])
    extra_robot = robot[:12] + np.array([0.0, 0.0, 15.0 * 6])
    to_image = lambda p: p @ image_from_robot[:3, :3].T + image_from_robot[:3, 3]  # noqa: E731
    return robot, to_image(robot), to_image(extra_robot)


def test_far_more_detections_than_spheres_is_refused_naming_the_phantom_file() -> None:
    robot, image, extra = _scene()
    assert len(robot) == 28
    with pytest.raises(PhantomMismatchError, match="40 spheres detected but the phantom file has 28") as e:
        register_points(robot, np.vstack([image, extra]))
    assert "check the phantom file" in str(e.value) and "--phantom-confirmed" in str(e.value)
    res = register_points(robot, np.vstack([image, extra]), params=replace(P, phantom_confirmed=True))
    assert res.n_matched == 28


@pytest.mark.parametrize(
    ("expected", "detected", "matched", "refused"),
    [
        (28, 40, 18, True),  # the scan: 40 > 1.25 × 28
        (40, 28, 18, True),  # 28-sphere phantom read with a 40-sphere file: 18/28 = 64 %
        (28, 30, 28, False),  # two stray blobs
        (28, 8, 8, False),  # a subset in the field of view
        (28, 9, 6, False),  # three leftovers: too few to question the file
        (28, 34, 28, False),
    ],
)
def test_the_phantom_fit_rule(expected: int, detected: int, matched: int, refused: bool) -> None:
    if refused:
        with pytest.raises(PhantomMismatchError, match="check the phantom file"):
            check_phantom_fit(expected, detected, matched, P)
        check_phantom_fit(expected, detected, matched, replace(P, phantom_confirmed=True))
    else:
        check_phantom_fit(expected, detected, matched, P)


def test_the_fre_gate_names_the_phantom_file_among_the_causes() -> None:
    """A phantom file 1 % smaller than the phantom scanned (14.85 mm pitch for 15): the FRE gate
    refuses (at a 0.2 mm gate: the error is ≈ 0.3 mm), naming the file."""
    robot, image, _ = _scene()
    shrunk = robot.mean(axis=0) + (robot - robot.mean(axis=0)) * 0.99
    with pytest.raises(AccuracyGateError, match="the phantom file does not describe the phantom scanned"):
        register_points(shrunk, image, params=replace(P, max_fre_mm=0.2))


def test_the_api_field_confirms_the_phantom_for_one_registration() -> None:
    """``POST /register {"phantom_confirmed": true}`` reaches the registration's parameters."""
    from registration.pipeline import PipelineParams
    from service.http.api.models import RegisterRequest
    from service.registrations.orchestrator import _confirmed

    assert RegisterRequest.model_validate({"phantom_confirmed": True}).phantom_confirmed is True
    assert RegisterRequest().phantom_confirmed is False
    params = PipelineParams()
    assert _confirmed(params).registration.phantom_confirmed and not params.registration.phantom_confirmed
