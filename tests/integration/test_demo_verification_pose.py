"""The demo verifies at a pose that moves the shoulder and elbow, with every sphere in the O-arm's
field, and says what one verification cannot show (issue 42, item 7).  Checked with the simulator's
own volume and the demo's true cell (no scan is simulated)."""

from __future__ import annotations

import numpy as np
import pytest

from service.cli.commands import demo


def test_the_verification_pose_moves_shoulder_and_elbow() -> None:
    delta = np.asarray(demo.Q2_DELTA_RAD)
    assert abs(delta[1]) >= np.radians(5.0) and abs(delta[2]) >= np.radians(5.0), delta
    assert "does not bound the error elsewhere" in demo.VERIFICATION_CAVEAT


@pytest.mark.parametrize("preset", ["demo", "small"])
def test_every_sphere_stays_in_the_field_at_the_verification_pose(preset: str) -> None:
    from mocks.cell import TrueCell
    from mocks.oarm.simulator import AcquisitionSettings, demo_pose
    from registration.calibration.sampling import ScanVolume
    from registration.io.resources import default_phantom
    from registration.model.frames import apply, invert
    from registration.model.kinematics import RobotModel, default_tool0_from_phantom
    from registration.model.phantom import load_phantom

    phantom = load_phantom(default_phantom())
    model, rod = RobotModel.load("tx60"), default_tool0_from_phantom()
    cell = TrueCell.sample(demo.TRUE_CELL_SEED, model, rod)
    q1 = np.asarray(demo.Q1_RAD)
    hidden = demo_pose() @ invert(cell.robot_from_tool0_true(q1) @ cell.tool0_from_phantom)
    s = AcquisitionSettings.preset(preset)
    volume = ScanVolume(fov_radius_mm=s.fov_radius_mm, half_length_mm=s.n_slices * s.slice_spacing_mm / 2)
    radius_mm = phantom.sphere_diameter_mm / 2.0
    for q in (q1, q1 + np.asarray(demo.Q2_DELTA_RAD)):
        centres = apply(
            hidden @ cell.robot_from_tool0_true(q) @ cell.tool0_from_phantom, phantom.centres_phantom_mm
        )
        margin = float(volume.inside_margin_mm(centres[None])[0])
        assert margin > radius_mm, (preset, q.tolist(), margin)
