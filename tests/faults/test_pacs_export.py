"""The PACS archive loses nothing (issue #23): the PACS down for a while, the service SIGKILLed in
the middle of a C-STORE and restarted.

The PACS is a pynetdicom Storage SCP on loopback under the test's control (it can hold a C-STORE
until released, so the kill lands mid-send for certain).  Phase 1 runs the service in-process,
phases 2 and 3 as ``python -m service.cli serve`` on the same data folder.
"""

from __future__ import annotations

import contextlib
import sqlite3
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
from pynetdicom import AE, evt

from tests.faults._service import ServeProcess, free_port, write_config
from tests.integration.peer_service import TOKEN, running_service, send_files, simulated_series, wait_for

PACS_AET = "TESTPACS"
SRO_CLASS = "1.2.840.10008.5.1.4.1.1.66.1"
HOLD_S = 60.0
"""Longest a held C-STORE waits for the test to release it."""


@dataclass
class Pacs:
    """A Storage SCP for Spatial Registration objects; ``hold`` keeps each C-STORE open until
    ``release`` is set (the response is never sent if the peer died meanwhile)."""

    port: int
    hold: bool = False
    received: list[str] = field(default_factory=list)
    arrived: threading.Event = field(default_factory=threading.Event)
    release: threading.Event = field(default_factory=threading.Event)

    def on_store(self, event: Any) -> int:
        self.received.append(str(event.dataset.SOPInstanceUID))
        self.arrived.set()
        if self.hold:
            self.release.wait(HOLD_S)
        return 0x0000


@contextlib.contextmanager
def running_pacs(pacs: Pacs) -> Iterator[Pacs]:
    ae = AE(ae_title=PACS_AET)
    ae.add_supported_context(SRO_CLASS)
    server = ae.start_server(
        ("127.0.0.1", pacs.port), block=False, evt_handlers=[(evt.EVT_C_STORE, pacs.on_store)]
    )
    try:
        yield pacs
    finally:
        pacs.release.set()
        server.shutdown()


def export_row(db: Path, registration_id: int) -> dict[str, Any]:
    """The queue row as stored, read-only (the service may be dead)."""
    with contextlib.closing(sqlite3.connect(f"file:{db}?mode=ro", uri=True)) as c:
        c.row_factory = sqlite3.Row
        r = c.execute("SELECT * FROM pacs_exports WHERE registration_id = ?", (registration_id,)).fetchone()
        assert r is not None, f"registration {registration_id} was never queued"
        return dict(r)


def api_export(client: httpx.Client, registration_id: int) -> dict[str, Any] | None:
    exp: dict[str, Any] | None = client.get(f"/registrations/{registration_id}").json().get("pacs_export")
    return exp


def test_pacs_down_then_killed_mid_send_loses_nothing(tmp_path: Path, phantom: Any) -> None:
    from mocks.robot.robot import ScriptedRobot
    from mocks.robot.runner import run_mock_controller
    from tests.integration.peer_service import Q1

    pacs_port = free_port()
    pacs_cfg = {"pacs.host": "127.0.0.1", "pacs.port": pacs_port, "pacs.ae_title": PACS_AET,
                "pacs.retry_initial_s": 0.1, "pacs.retry_max_s": 0.4, "pacs.timeout_s": 5.0}  # fmt: skip

    # 1. in-process: the PACS is down when the registration is accepted → pending, retried; up → sent
    with running_service(tmp_path, phantom, **pacs_cfg) as svc:
        uid, files = simulated_series(phantom, tmp_path / "outbox")
        assert set(send_files(svc.dicom_port, files)) == {0}
        reg1 = svc.wait_registration(svc.wait_scan(uid)["id"])["id"]
        down = wait_for(
            lambda: (e := api_export(svc.client, reg1)) and e["attempts"] >= 3 and e, "3 failed attempts"
        )
        assert down["state"] == "pending" and "no association" in down["reason"], down
        with running_pacs(Pacs(pacs_port)) as pacs:
            sent = wait_for(
                lambda: (e := api_export(svc.client, reg1)) and e["state"] == "sent" and e, "sent"
            )
        assert pacs.received == [sent["sop_instance_uid"]] and sent["dimse_status"] == 0
        assert sent["attempts"] > down["attempts"]
        # a second registration while the PACS is down again; the service then stops cleanly
        r = svc.client.post("/register", json={"scan_id": svc.wait_scan(uid)["id"]})
        assert r.status_code == 200, r.text
        reg2 = r.json()["id"]
        wait_for(
            lambda: (e := api_export(svc.client, reg2)) and e["attempts"] >= 1, "a failed attempt of reg 2"
        )
    db = tmp_path / "data" / "oarmreg.sqlite3"
    assert export_row(db, reg2)["state"] == "pending"

    robot = ScriptedRobot(Q1)
    with run_mock_controller("simple-message", robot) as mock:
        cfg, port = tmp_path / "serve.toml", free_port()
        write_config(cfg, {"watch_dir": str(tmp_path / "watch"), "data_dir": str(tmp_path / "data"),
                           "api_token": TOKEN, "port": port, "robot.link_url": mock.url,
                           "robot.connect_timeout_s": 2.0, **pacs_cfg})  # fmt: skip
        proc = ServeProcess(cfg, port, tmp_path / "serve.log")
        try:
            # 2. the restarted service resumes the queue; SIGKILL while the PACS holds the C-STORE
            with running_pacs(Pacs(pacs_port, hold=True)) as held:
                proc.start()
                assert held.arrived.wait(HOLD_S), "the restarted service never sent the pending export"
                proc.kill9()
            before = export_row(db, reg2)
            assert before["state"] == "pending", before  # nothing claims it was sent
            # 3. restarted again, the PACS answering: the same instance arrives and is recorded sent
            with running_pacs(Pacs(pacs_port)) as pacs:
                proc.start()
                with httpx.Client(base_url=proc.base_url, headers={"Authorization": f"Bearer {TOKEN}"}) as c:
                    done = wait_for(
                        lambda: (e := api_export(c, reg2)) and e["state"] == "sent" and e, "reg 2 sent"
                    )
                    audit = c.get("/audit").json()
                    reg1_after = api_export(c, reg1)
        finally:
            proc.stop()
    assert held.received == [done["sop_instance_uid"]]  # the killed attempt carried the same instance
    assert pacs.received == [done["sop_instance_uid"]]
    assert reg1_after is not None and reg1_after["state"] == "sent"  # not sent twice
    assert [a["outcome"] for a in audit if a["action"] == "pacs_export" and a["target_id"] == reg2] == [
        "sent"
    ]
