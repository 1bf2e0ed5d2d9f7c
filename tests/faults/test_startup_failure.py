"""A start-up that fails half-way stops what it had started and leaves the data folder usable.

The C-STORE port is held by another socket, so the lifespan fails at the last part it starts: by
then the database is open, the robot link's reader runs, the calibration worker, auto-register's
thread, the OpenIGTLink server and the folder watcher are up.  Each must be stopped again: no thread
or task is left (the autouse guard of ``tests/conftest.py`` fails the test otherwise), the serve
lock and the database are released (the next start on the same folder succeeds), and no context
was published half-built (``app.state.ctx`` is not set).
"""

from __future__ import annotations

import asyncio
import socket
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.faults.conftest import AUTH, fault_settings


def _lifespan_once(app: Any) -> None:
    async def run() -> None:
        async with app.router.lifespan_context(app):
            pass

    asyncio.run(run())


def test_a_start_up_failing_half_way_stops_what_had_started(tmp_path: Path, phantom: Any) -> None:
    from registration.model.kinematics import RobotModel
    from service.errors import DicomScpConfigError
    from service.http.app import create_app

    model = RobotModel.load("tx60")
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        settings = fault_settings(
            tmp_path,
            **{"dicom.enabled": True, "dicom.port": port, "igtl.enabled": True, "igtl.port": 0,
               "service.auto_register": True},
        )  # fmt: skip
        app = create_app(settings, phantom=phantom, robot_model=model)
        with pytest.raises(DicomScpConfigError, match="Address already in use"):
            _lifespan_once(app)
        assert not hasattr(app.state, "ctx")

    # the same folder starts again (the lock and the database were released) and serves
    from service.cli.commands.serve import serve_in_thread

    again = create_app(fault_settings(tmp_path), phantom=phantom, robot_model=model)
    with serve_in_thread(again) as server, httpx.Client(base_url=server.base_url, headers=AUTH) as client:
        r = client.get("/status")
        assert r.status_code == 200, r.text
        assert r.json()["listeners"]["dicom"] == {
            "enabled": False, "host": "127.0.0.1", "ae_title": "OARMREG", "port": None
        }  # fmt: skip
