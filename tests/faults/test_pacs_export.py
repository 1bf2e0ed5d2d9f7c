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
    answers: list[int] = field(default_factory=list)
    """Statuses to answer, one per C-STORE, before Success (e.g. 0xA700 while "out of resources")."""
    received: list[str] = field(default_factory=list)
    arrived: threading.Event = field(default_factory=threading.Event)
    release: threading.Event = field(default_factory=threading.Event)

    def on_store(self, event: Any) -> int:
        self.received.append(str(event.dataset.SOPInstanceUID))
        self.arrived.set()
        if self.hold:
            self.release.wait(HOLD_S)
        return self.answers.pop(0) if self.answers else 0x0000


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


def _accepted_registration(db: Any, n: int) -> int:
    """An accepted registration with its scan's instance UIDs, written through the service's store
    (what the SRO is built from), without running detection: the test is about the send."""
    from service.records import NewScan, RegistrationFigures, RegistrationRecord
    from service.store.scan_instances import ScanInstances

    series = f"1.2.826.0.1.3680043.10.1432.{n}"
    sid, _ = db.scans.upsert(NewScan(series_uid=series, folder=f"/scan{n}", status="complete"))
    db.scan_instances.put(
        ScanInstances(series_uid=series, study_uid=series + ".1", frame_of_reference_uid=series + ".2",
                      sop_class_uids=("1.2.840.10008.5.1.4.1.1.2",), sop_instance_uids=(series + ".3",))
    )  # fmt: skip
    figures = RegistrationFigures(
        fle_mm=0.1, n_expected=28, n_detected=28, n_matched=28, symmetry_margin=12, rotation_det=1.0,
        predicted_tre_mm=(0.1,), targets_image_mm=((0.0, 0.0, 0.0),), targets_source="request",
        spheres=(), provenance={"series_uid": series},
    )  # fmt: skip
    identity = ((1.0, 0.0, 0.0, 0.0), (0.0, 1.0, 0.0, 0.0), (0.0, 0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    rid: int = db.registrations.insert(
        RegistrationRecord(created_at="2026-01-01T00:00:00+00:00", status="accepted", config_hash="t",
                           software_version="t", scan_id=sid, series_uid=series, image_from_robot=identity,
                           fre_mm=0.1, figures=figures),
        make_current=True,
    )  # fmt: skip
    return rid


def test_out_of_resources_is_retried_and_a_permanent_error_stops(tmp_path: Path) -> None:
    """Issue #32 item 6: the PACS answers 0xA700 (Refused: Out of Resources, transient in PS3.4
    B.2.3) twice, then "recovers": sent on the third attempt.  0xA900 (data set does not match the
    SOP class, permanent): failed after one attempt, naming the status.  The real exporter and SCU
    against a pynetdicom Storage SCP on loopback."""
    from service.navigation.pacs.exporter import PacsExporter
    from service.settings import PacsSettings
    from service.store import Database

    pacs_port = free_port()
    cfg = PacsSettings(host="127.0.0.1", port=pacs_port, ae_title=PACS_AET, retry_initial_s=0.1,
                       retry_max_s=0.4, timeout_s=5.0)  # fmt: skip
    db = Database.open(tmp_path / "oarmreg.sqlite3")
    events: list[Any] = []
    exporter = PacsExporter(db, cfg, tmp_path, events.append)
    try:
        with running_pacs(Pacs(pacs_port, answers=[0xA700, 0xA700])) as pacs:
            exporter.start()
            reg1 = _accepted_registration(db, 1)
            exporter.enqueue(reg1)
            sent = wait_for(
                lambda: (e := db.pacs_exports.get(reg1)) and e.state != "pending" and e, "reg 1 done"
            )
            assert sent.state == "sent" and sent.dimse_status == 0 and sent.attempts == 3, sent
            assert pacs.received == [sent.sop_instance_uid] * 3  # two refusals, then stored

            pacs.answers = [0xA900]
            reg2 = _accepted_registration(db, 2)
            exporter.enqueue(reg2)
            failed = wait_for(
                lambda: (e := db.pacs_exports.get(reg2)) and e.state != "pending" and e, "reg 2"
            )
            assert failed.state == "failed" and failed.attempts == 1, failed
            assert failed.dimse_status == 0xA900 and "status 0xA900" in failed.reason, failed
            assert "permanent" in failed.reason
    finally:
        exporter.stop()
        db.close()
    assert [type(e).__name__ for e in events] == ["PacsExportSent", "PacsExportFailed"]
