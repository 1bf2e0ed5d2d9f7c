"""Modbus TCP link against a real pymodbus server on loopback (issue #5)."""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest
from polling import wait_until

from drivers.errors import LinkConfigError, LinkTimeoutError
from drivers.factory import open_link
from drivers.modbus import RegisterMap, joints_to_registers, registers_to_joints
from mocks.robot.robot import ScriptedRobot
from mocks.robot.runner import run_mock_controller

Q_DEG = (12.5, -33.25, 101.0, -7.75, 44.125, 170.0)
Q = [math.radians(d) for d in Q_DEG]


def test_float32_degrees_exact_and_polls_not_lost() -> None:
    rmap = RegisterMap(start_address=100, word_order="big", units="deg")

    async def main() -> None:
        with run_mock_controller("modbus", ScriptedRobot(Q), register_map=rmap) as mock:
            link = open_link(mock.url)
            await link.connect()
            expected = tuple(math.radians(float(np.float32(d))) for d in Q_DEG)
            assert link.latest().joints_rad == expected  # the float32 the controller wrote, exactly
            # 80 polls (1.6 s at 50 Hz), waited for by count, not by time: a loaded machine polls slower
            await wait_until(lambda: link.counters()["frames_accepted"] >= 80, "80 polls", 30.0)
            await link.close()
            sent, got = mock.frames_sent(), link.counters()["frames_accepted"]
            assert got >= 80
            assert 0 <= sent - got <= 1  # none lost: at most the one request in flight at close
            assert link.counters()["frames_rejected"] == 0

    asyncio.run(main())


@pytest.mark.parametrize(
    ("rmap", "tol_rad"),
    [
        (RegisterMap(data_type="float32", word_order="little", units="rad", function_code=4), 0.0),
        (RegisterMap(data_type="int32", units="deg", scale=1e-4, start_address=7), math.radians(0.5e-4)),
        (RegisterMap(data_type="int16", units="deg", scale=0.01, unit_id=3), math.radians(0.005)),
    ],
)
def test_register_map_variants(rmap: RegisterMap, tol_rad: float) -> None:
    async def main() -> None:
        with run_mock_controller("modbus", ScriptedRobot(Q), register_map=rmap) as mock:
            async with open_link(mock.url) as link:
                got = np.array(link.latest().joints_rad)
                want = np.array(Q, dtype=np.float32) if tol_rad == 0 else np.array(Q)
                if tol_rad == 0:
                    assert np.array_equal(got.astype(np.float32), want)
                else:
                    assert np.max(np.abs(got - want)) <= tol_rad + 1e-12

    asyncio.run(main())


def test_codec_word_order_matches_pymodbus_convention() -> None:
    # 1.2345 as float32 big word order = [0x3F9E, 0x0419] (research/staubli-link.md §2.1)
    rm = RegisterMap(units="rad", n_joints=1)
    assert joints_to_registers([1.2345], rm) == [0x3F9E, 0x0419]
    assert joints_to_registers([1.2345], RegisterMap(units="rad", n_joints=1, word_order="little")) == [
        0x0419, 0x3F9E,
    ]  # fmt: skip
    assert registers_to_joints([0x3F9E, 0x0419], rm)[0] == pytest.approx(1.2345, abs=1e-7)


def test_url_query_configures_the_map() -> None:
    link = open_link("modbus://10.0.0.2?unit=5&fc=4&address=200&type=int16&word_order=little&units=rad"
                     "&scale=0.001&poll_hz=25")  # fmt: skip
    rm = link.register_map  # type: ignore[attr-defined]
    assert (rm.unit_id, rm.function_code, rm.start_address, rm.data_type) == (5, 4, 200, "int16")
    assert (rm.word_order, rm.units, rm.scale, rm.poll_hz) == ("little", "rad", 0.001, 25.0)
    assert link.port == 502 and link.stale_after_s == pytest.approx(3 / 25)  # type: ignore[attr-defined]
    with pytest.raises(LinkConfigError, match="function code"):
        open_link("modbus://10.0.0.2?fc=16")
    with pytest.raises(LinkConfigError, match="word order"):
        open_link("modbus://10.0.0.2?word_order=middle")


def test_nan_rejected() -> None:
    async def main() -> None:
        with run_mock_controller("modbus", ScriptedRobot(Q)) as mock:
            async with open_link(mock.url) as link:
                mock.inject_nan(n_frames=2, joint=1)
                await wait_until(lambda: link.counters()["frames_rejected"] >= 2, "2 rejected reads")
                n = link.counters()["frames_accepted"]
                await wait_until(lambda: link.counters()["frames_accepted"] > n, "a good read after")
                assert all(math.isfinite(v) for s in link.history(0.0) for v in s.joints_rad)

    asyncio.run(main())


def test_garbage_response_never_published() -> None:
    async def main() -> None:
        with run_mock_controller("modbus", ScriptedRobot(Q)) as mock:
            async with open_link(mock.url, silence_reconnect_s=0.3) as link:
                mock.inject_garbage(b"\x00\x01\x00\x00\x00\x03\x01\x83\x02" + b"\xff" * 20)
                n = link.counters()["frames_accepted"]
                await wait_until(lambda: link.counters()["frames_accepted"] > n + 5, "reads after garbage")
                want = tuple(math.radians(float(np.float32(d))) for d in Q_DEG)
                assert all(s.joints_rad == want for s in link.history(0.0))

    asyncio.run(main())


def test_wrong_address_gives_modbus_exception_message() -> None:
    async def main() -> None:
        with run_mock_controller("modbus", ScriptedRobot(Q)) as mock:
            url = mock.url.replace("address=0", "address=50")
            link = open_link(url)
            with pytest.raises(LinkTimeoutError, match="Modbus exception"):
                await link.connect(timeout_s=0.5)

    asyncio.run(main())


def test_back_within_1s_and_stale_on_stall() -> None:
    async def main() -> None:
        with run_mock_controller("modbus", ScriptedRobot(Q)) as mock:
            async with open_link(mock.url) as link:
                mock.stall()
                await wait_until(lambda: link.health().state == "stale", "stale", 2.0)
                last = link.latest().t_s
                assert link.health(now_t_s=last + 0.061).state == "stale"
                mock.resume()
                await wait_until(lambda: link.health().state == "connected", "connected again")
                back = asyncio.create_task(asyncio.to_thread(mock.disconnect, 0.5))
                await wait_until(lambda: link.health().state == "down", "down")
                t_return = await back
                await wait_until(lambda: link.latest().t_s > t_return, "a read after the return", 1.0)

    asyncio.run(main())
