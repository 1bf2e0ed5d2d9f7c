"""Issue 40 item 5: a joint at its limit, read over each link, is at the limit, not beyond it.

The real mock controllers serve the TX60 at all six lower limits, then all six upper limits (the 12
limit values of configs/robots/tx60.urdf), and the real drivers read them.  The wire rounds: float32
over simple_message (J1 = 180°, J4 = ±270°… come back up to 2.4e-7 rad beyond), 9 significant digits
over serial (J2 ±127.5°, J5 +132.5° come back 5e-9 rad beyond), the register type over Modbus.  Each
link states its rounding (``joint_resolution_rad``); the decoded value lies within it of the value
sent, and the limit check with it returns the limit itself.  Before, the check allowed 1e-9 rad
whatever the wire, and "check the joint units" was the hint.
"""

from __future__ import annotations

import asyncio
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from polling import wait_until

from drivers.factory import open_link
from drivers.modbus import RegisterMap
from mocks.robot.robot import ScriptedRobot
from mocks.robot.runner import run_mock_controller
from registration.errors import KinematicsError
from registration.model.kinematics import RobotModel
from service.intake.capture import Capture

TX60 = RobotModel.load("tx60")
POSES = {"lower": tuple(TX60.lower_rad.tolist()), "upper": tuple(TX60.upper_rad.tolist())}

LINKS: dict[str, tuple[str, dict[str, Any]]] = {
    "simple-message": ("simple-message", {}),
    "serial": ("serial", {}),
    "modbus float32 deg": ("modbus", {"register_map": RegisterMap(data_type="float32", units="deg")}),
    "modbus float32 rad": ("modbus", {"register_map": RegisterMap(data_type="float32", units="rad")}),
    "modbus int16 0.01 deg": (
        "modbus",
        {"register_map": RegisterMap(data_type="int16", units="deg", scale=0.01)},
    ),
}


def _read_at(link: Any, robot: ScriptedRobot, pose: tuple[float, ...]) -> tuple[float, ...]:
    robot.hold(pose)

    async def main() -> tuple[float, ...]:
        def near() -> bool:
            last = link.latest()
            return last is not None and bool(np.allclose(last.joints_rad, pose, atol=1e-3))

        await wait_until(near, "the link to read the pose", 10.0)
        return tuple(link.latest().joints_rad)

    return asyncio.run(main())


@pytest.mark.parametrize("name", sorted(LINKS))
def test_all_twelve_tx60_limit_values_are_at_the_limit_over_every_link(name: str) -> None:
    kind, options = LINKS[name]
    robot = ScriptedRobot(POSES["lower"])
    with run_mock_controller(kind, robot, **options) as mock:
        link = open_link(mock.url)
        link.start()
        try:
            for side, pose in POSES.items():
                got = _read_at(link, robot, pose)
                res = link.joint_resolution_rad(got)
                for j, (g, sent, r) in enumerate(zip(got, pose, res, strict=True)):
                    assert abs(g - sent) <= r + 1e-15, (
                        name,
                        side,
                        j + 1,
                        g - sent,
                        r,
                    )  # the stated rounding holds
                q = TX60.check_joints(got, resolution_rad=res)
                assert q.tolist() == list(pose), (name, side, (np.asarray(got) - pose).tolist())
        finally:
            asyncio.run(link.close())


def test_the_wire_rounding_is_what_refused_them_before() -> None:
    """simple_message and serial put some limit values beyond the limit by more than 1e-9 rad."""
    beyond = []
    robot = ScriptedRobot(POSES["upper"])
    for kind in ("simple-message", "serial"):
        with run_mock_controller(kind, robot) as mock:
            link = open_link(mock.url)
            link.start()
            try:
                for side, pose in POSES.items():
                    got = _read_at(link, robot, pose)
                    try:
                        TX60.check_joints(got)
                    except KinematicsError as e:
                        beyond.append((kind, side, str(e)))
            finally:
                asyncio.run(link.close())
    assert {k for k, _, _ in beyond} == {"simple-message", "serial"}, beyond
    assert all("units" not in msg and "encoding can round" in msg for _, _, msg in beyond)


def test_capture_records_the_limit_not_the_wires_rounding(tmp_path: Path) -> None:
    from service.settings import load_settings

    settings = load_settings(None, {"watch_dir": tmp_path / "w", "data_dir": tmp_path / "d"})
    robot = ScriptedRobot(POSES["upper"])
    with run_mock_controller("simple-message", robot) as mock:
        link = open_link(mock.url)
        link.start()
        try:
            got = _read_at(link, robot, POSES["upper"])
            assert any(g > u for g, u in zip(got, POSES["upper"], strict=True))  # float32 rounded up
            last = link.latest().t_s
            snap = Capture(link, settings, lambda e: None).snapshot(last, last)
            assert snap.joints_rad == POSES["upper"]
        finally:
            asyncio.run(link.close())


def test_cli_robot_points_reads_the_limit_not_the_wires_rounding(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """``oarmreg robot points`` at the upper limits over simple_message: float32 puts some joints
    beyond them; the points are computed (not refused) at the limits themselves."""
    import json

    from service.cli.main import main

    with run_mock_controller("simple-message", ScriptedRobot(POSES["upper"])) as mock:
        argv = ["robot", "points", "--link", mock.url, "--still-window-s", "0.2"]
        assert main(argv) == 0, capsys.readouterr().err
    doc = json.loads(capsys.readouterr().out)
    assert doc["joints_rad"] == list(POSES["upper"])


def test_a_value_beyond_the_rounding_is_refused_with_a_hint_that_fits() -> None:
    upper = np.array(POSES["upper"])
    res = [2.4e-7] * 6
    with pytest.raises(KinematicsError, match=r"joint_4 .* beyond it, more than .* the robot model") as e:
        TX60.check_joints(upper + np.array([0, 0, 0, 1e-5, 0, 0]), resolution_rad=res)
    assert "degrees" not in str(e.value)
    looks_like_degrees = [0.0, 0.0, 90.0, 0.0, 0.0, 0.0]  # J3 = 90 sent as if it were radians
    with pytest.raises(KinematicsError, match=r"90 looks like degrees \(1\.5708 rad would be inside"):
        TX60.check_joints(looks_like_degrees)
    assert math.isclose(TX60.at_limits(upper + 1e-7, 2.4e-7)[0], upper[0])
