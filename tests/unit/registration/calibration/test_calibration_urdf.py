"""The numpy chain read from the URDF and the calibrated-URDF writer (issue #10 outputs)."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from registration.calibration.urdf import read_chain, rotation_about, write_calibrated_urdf
from registration.errors import ConfigError
from registration.model import frames
from registration.model.kinematics import RobotModel

# joint vectors spanning the limits of every joint (rad)
JOINTS = np.array(
    [
        [0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        [0.2, -0.15, 1.75, 0.3, 0.6, -0.9],
        [-3.0, 2.1, -2.4, 4.6, -2.0, -4.6],
        [3.0, -2.1, 2.4, -4.6, 2.2, 4.6],
        [1.1, 0.7, -0.3, 2.0, -1.3, 0.4],
    ]
)
FK_EXACT_MM = 1e-9
"""Issue #10: the written URDF reproduces the calibrated FK to 1e-9 mm."""


@pytest.mark.parametrize("name", ["tx60", "tx2_60"])
def test_chain_equals_pinocchio_fk(name: str) -> None:
    model = RobotModel.load(name)
    chain = read_chain(model.urdf_path)
    assert chain.joint_names == model.joint_names
    np.testing.assert_array_equal(chain.lower_rad, model.lower_rad)
    for q in JOINTS:
        q = np.clip(q, model.lower_rad, model.upper_rad)
        assert np.abs(chain.robot_from_tool0(q) - model.robot_from_tool0(q)).max() <= FK_EXACT_MM


def _perturbed(name: str):  # type: ignore[no-untyped-def]
    chain = read_chain(RobotModel.load(name).urdf_path)
    m = chain.parent_from_joint.copy()
    for i in range(chain.n_joints):
        axis = np.array([math.sin(i + 1.0), math.cos(2.0 * i), 0.3 * i + 0.1])
        axis /= np.linalg.norm(axis)
        m[i] = m[i] @ frames.make_transform(
            rotation_about(axis, np.array([1e-3 * (i + 1)]))[0], [0.1 * i, -0.2, 0.05 * i]
        )
    tool = chain.last_from_tool0 @ frames.transform_from_xyz_rpy([0.3, -0.1, 0.2], [0.05, -0.02, 0.1])
    return chain.with_origins(m, tool)


@pytest.mark.parametrize("name", ["tx60", "tx2_60"])
def test_written_urdf_loads_back_to_the_same_fk(name: str, tmp_path: Path) -> None:
    calibrated = _perturbed(name)
    path = write_calibrated_urdf(calibrated, tmp_path / "robot.urdf", comment="oarmreg calibration test-123")
    loaded = RobotModel.load(path)
    for q in JOINTS:
        q = np.clip(q, loaded.lower_rad, loaded.upper_rad)
        assert np.abs(loaded.robot_from_tool0(q) - calibrated.robot_from_tool0(q)).max() <= FK_EXACT_MM
    # and it is really different from the nominal model (the test can fail)
    nominal = RobotModel.load(name)
    assert np.abs(loaded.robot_from_tool0(JOINTS[1]) - nominal.robot_from_tool0(JOINTS[1])).max() > 0.1


def test_written_urdf_keeps_links_joints_and_names_the_calibration(tmp_path: Path) -> None:
    nominal_path = RobotModel.load("tx60").urdf_path
    path = write_calibrated_urdf(
        _perturbed("tx60"), tmp_path / "robot.urdf", comment="calibration 2026-12-01 abc"
    )
    text = path.read_text(encoding="utf-8")
    assert "<!-- calibration 2026-12-01 abc -->" in text
    a, b = ET.parse(nominal_path).getroot(), ET.parse(path).getroot()
    assert [ln.get("name") for ln in a.iter("link")] == [ln.get("name") for ln in b.iter("link")]
    joints_a = [(j.get("name"), j.get("type"), j.find("parent").get("link")) for j in a.iter("joint")]  # type: ignore[union-attr]
    joints_b = [(j.get("name"), j.get("type"), j.find("parent").get("link")) for j in b.iter("joint")]  # type: ignore[union-attr]
    assert joints_a == joints_b
    for ja, jb in zip(a.iter("joint"), b.iter("joint"), strict=True):
        for tag in ("axis", "limit"):
            ea, eb = ja.find(tag), jb.find(tag)
            assert (ea is None) == (eb is None) and (ea is None or ea.attrib == eb.attrib)  # type: ignore[union-attr]
    # the mounting-surface joint before joint_1 is untouched
    base = next(j for j in b.iter("joint") if j.get("name") == "base-base_link")
    assert base.find("origin").get("xyz") == "0 0 -0.375"  # type: ignore[union-attr]


def test_chain_without_tool0_is_a_config_error(tmp_path: Path) -> None:
    bad = tmp_path / "bad.urdf"
    bad.write_text(
        '<robot name="x"><link name="base"/><link name="a"/>'
        '<joint name="j" type="revolute"><parent link="base"/><child link="a"/></joint></robot>'
    )
    with pytest.raises(ConfigError, match="no joint chain from 'base' to 'tool0'"):
        read_chain(bad)
