"""The service runs without HTTP: ``running_service`` starts every part, the robot link connects,
and leaving it stops them all (the module's leak guard fails on a thread left behind)."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

from mocks.robot.robot import ScriptedRobot
from mocks.robot.runner import run_mock_controller
from service.runtime.assembly import running_service
from service.runtime.inputs import prepare_inputs
from service.settings import load_settings
from tests.helpers.tokens import make_token
from tests.integration.polling import wait_until

Q = (0.0, 0.0, 1.5707963267948966, 0.0, 0.7853981633974483, 0.0)
DEADLINE_S = 30.0


def test_the_service_runs_and_stops_without_a_web_server(tmp_path: Path, phantom: Any) -> None:
    with run_mock_controller("simple-message", ScriptedRobot(Q)) as mock:
        settings = load_settings(
            None,
            {
                "data_dir": tmp_path / "data", "watch_dir": tmp_path / "watch", "robot.link_url": mock.url,
                "api_token": make_token(),  # checked by prepare_inputs, though nothing serves HTTP here
            },
        )  # fmt: skip
        inputs = prepare_inputs(settings, phantom=phantom)

        async def run() -> dict[str, Any]:
            async with running_service(inputs, start_watcher=False) as ctx:
                assert ctx.watcher is None and ctx.orchestrator.current is None
                await wait_until(
                    lambda: ctx.capture.health()["state"] == "connected", "the robot link", DEADLINE_S
                )
                return {"health": ctx.capture.health(), "counts": ctx.db.counts()}

        seen = asyncio.run(run())
    assert seen["health"]["state"] == "connected", seen
    assert seen["counts"]["registrations"] == 0, seen
    assert (tmp_path / "data" / "oarmreg.sqlite3").is_file()
