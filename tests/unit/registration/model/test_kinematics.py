"""Forward kinematics of the project's TX60 / TX2-60 URDFs (issue #5)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from registration.errors import ConfigError, KinematicsError, OarmRegError
from registration.model.frames import transform_from_xyz_rpy
from registration.model.kinematics import RobotModel, default_tool0_from_phantom, sphere_centres_robot_mm

REFERENCE = Path(__file__).resolve().parents[3] / "data" / "reference_robots"
"""Reference values carried into the repository; origin: tests/data/reference_robots/README.md."""
FK_JSON = REFERENCE / "fk_reference.json"
MODELS = [("tx60", "staubli_tx60"), ("tx2_60", "staubli_tx2_60")]
JSON_POSITION_ROUNDING_MM = 0.0005 + 1e-9
"""fk_reference.json prints positions to 3 decimals (mm) and rotations to 6."""
JSON_ROTATION_ROUNDING = 5e-7 + 1e-12
FK_TOL_MM = 1e-6
"""The issue's tolerance, applied against full-precision references."""


def _reference(path: Path) -> Path:
    """``path``, which the checkout carries: a missing file is a failure, never a skip."""
    assert path.is_file(), f"reference file {path} missing from the checkout"
    return path


def _configs(ref_name: str) -> list[tuple[str, list[float], dict]]:  # type: ignore[type-arg]
    d = json.loads(_reference(FK_JSON).read_text())["robots"][ref_name]["fk"]
    return [(k, v["q_deg"], v) for k, v in d.items()]


def _mdh(alpha_deg: float, a_mm: float, theta_rad: float, d_mm: float) -> np.ndarray:
    """Craig's modified DH link transform."""
    ca, sa = math.cos(math.radians(alpha_deg)), math.sin(math.radians(alpha_deg))
    ct, st = math.cos(theta_rad), math.sin(theta_rad)
    return np.array([[ct, -st, 0, a_mm], [st * ca, ct * ca, -sa, -sa * d_mm],
                     [st * sa, ct * sa, ca, ca * d_mm], [0, 0, 0, 1]])  # fmt: skip


def _independent_fk_mm(q_rad: np.ndarray) -> np.ndarray:
    """TX2-60 modified-DH table (7hub/robo_kin TX2_60.h, quoted in reference/robots/README.md),
    shifted down 375 mm so it is expressed in the Stäubli world frame (`base`)."""
    table = [
        (0, 0, 0, 375),
        (-90, 0, -90, 20),
        (0, 290, -90, 0),
        (-90, 0, 0, 310),
        (90, 0, 0, 0),
        (-90, 0, 180, 70),
    ]
    t = np.eye(4)
    t[2, 3] = -375.0
    for (alpha, a, off_deg, d), q in zip(table, q_rad, strict=True):
        t = t @ _mdh(alpha, a, q + math.radians(off_deg), d)
    return t


@pytest.mark.parametrize(("name", "ref_name"), MODELS)
def test_fk_matches_reference_table(name: str, ref_name: str) -> None:
    model = RobotModel.load(name)
    for key, q_deg, v in _configs(ref_name):
        t = model.robot_from_tool0(np.radians(q_deg))
        ref = v["tool0_in_base"]
        assert np.max(np.abs(t[:3, 3] - ref["p_mm"])) <= JSON_POSITION_ROUNDING_MM, key
        assert np.max(np.abs(t[:3, :3] - np.array(ref["R"]))) <= JSON_ROTATION_ROUNDING, key
        # base_link = mounting surface, 375 mm below our robot frame
        assert t[2, 3] + 375.0 == pytest.approx(
            v["tool0_in_base_link"]["p_mm"][2], abs=JSON_POSITION_ROUNDING_MM
        )


@pytest.mark.parametrize(("name", "ref_name"), MODELS)
def test_fk_matches_reference_urdf_within_1e6_mm(name: str, ref_name: str) -> None:
    import pinocchio as pin

    urdf = _reference(REFERENCE / f"{ref_name}.urdf")
    ref_model = pin.buildModelFromUrdf(str(urdf))
    data = ref_model.createData()
    model = RobotModel.load(name)
    qs = [np.radians(q) for _, q, _ in _configs(ref_name)] + [np.radians([33, -70, 110, -150, 80, -200])]
    for q in qs:
        pin.framesForwardKinematics(ref_model, data, q)
        m = data.oMf[ref_model.getFrameId("base")].actInv(data.oMf[ref_model.getFrameId("tool0")])
        t = model.robot_from_tool0(q)
        assert np.max(np.abs(t[:3, 3] - m.translation * 1000.0)) <= FK_TOL_MM
        assert np.max(np.abs(t[:3, :3] - m.rotation)) <= 1e-12
        # and an independent modified-DH formulation agrees too
        assert np.max(np.abs(t - _independent_fk_mm(q))) <= FK_TOL_MM


def test_zero_pose_known_answer() -> None:
    t = RobotModel.load("tx60").robot_from_tool0(np.zeros(6))
    assert np.allclose(t, [[1, 0, 0, 0], [0, 1, 0, 20], [0, 0, 1, 670], [0, 0, 0, 1]], atol=1e-9)


def test_limits_differ_between_tx60_and_tx2_60() -> None:
    a, b = RobotModel.load("tx60"), RobotModel.load("tx2_60")
    assert a.joint_names == b.joint_names == tuple(f"joint_{i}" for i in range(1, 7))
    assert math.degrees(a.upper_rad[2]) == pytest.approx(142.5) and math.degrees(
        b.upper_rad[2]
    ) == pytest.approx(152.5)
    assert math.degrees(a.lower_rad[4]) == pytest.approx(-122.5) and math.degrees(
        b.lower_rad[4]
    ) == pytest.approx(-121.0)
    q = np.radians([0, 0, 150, 0, 0, 0])
    b.robot_from_tool0(q)
    with pytest.raises(
        KinematicsError, match=r"joint_3 = 150\.0000° is outside its limit \[-142\.5000°, 142\.5000°\]"
    ):
        a.robot_from_tool0(q)


def test_wrong_joint_count() -> None:
    with pytest.raises(KinematicsError, match="expected 6 joint values"):
        RobotModel.load("tx60").robot_from_tool0([0.0] * 5)


def test_nan_joint() -> None:
    with pytest.raises(KinematicsError, match="joint_2"):
        RobotModel.load("tx60").robot_from_tool0([0, math.nan, 0, 0, 0, 0])


def test_limit_is_inclusive() -> None:
    m = RobotModel.load("tx60")
    m.robot_from_tool0(m.upper_rad)
    m.robot_from_tool0(m.lower_rad)


def test_unknown_model_and_missing_file() -> None:
    with pytest.raises(ConfigError, match="unknown robot model 'tx99'"):
        RobotModel.load("tx99")
    with pytest.raises(ConfigError, match="does not exist"):
        RobotModel.load("/nonexistent/robot.urdf")
    assert issubclass(KinematicsError, OarmRegError)


def test_load_by_path() -> None:
    m = RobotModel.load(str(Path(__file__).resolve().parents[4] / "configs" / "robots" / "tx2_60.urdf"))
    assert m.name == "tx2_60" and m.n_joints == 6


def test_sphere_centres_compose_fk_rod_and_phantom() -> None:
    model = RobotModel.load("tx60")
    q = np.radians([10, 20, 30, 40, 50, 60])
    rod = default_tool0_from_phantom()
    pts = np.array([[0.0, 0.0, 0.0], [35.0, 0.0, 0.0], [0.0, 0.0, 40.0]])
    out = sphere_centres_robot_mm(model, q, rod, pts)
    t = model.robot_from_tool0(q)
    # phantom centre: 200 mm along tool0 +z
    assert np.allclose(out[0], t[:3, 3] + 200.0 * t[:3, 2], atol=1e-9)
    # phantom +z points back at the flange (roll 180°)
    assert np.allclose(out[2] - out[0], -40.0 * t[:3, 2], atol=1e-9)
    assert out.shape == (3, 3)


def test_sphere_centres_reject_non_rigid_rod() -> None:
    model = RobotModel.load("tx60")
    bad = transform_from_xyz_rpy([0, 0, 200], [180, 0, 0])
    bad[:3, 0] *= -1  # mirror
    with pytest.raises(OarmRegError, match="reflection"):
        sphere_centres_robot_mm(model, np.zeros(6), bad, np.zeros((1, 3)))
