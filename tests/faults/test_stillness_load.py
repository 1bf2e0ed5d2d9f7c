"""Issue 19 item 7 under load, against the real service as the OR PC runs it: a still robot streaming
(``oarmreg mock robot``, 50 Hz simple_message, a process of its own) while 12 associations deliver
scans at once (dcmtk ``storescu`` processes, or pynetdicom threads where dcmtk is missing) and 200
OpenIGTLink clients connect and never read.  Every scan's stillness verdict must be ``still``.

The service is ``oarmreg serve`` (a subprocess, link reader in its child process, the default).
``[dicom] maximum_associations`` is raised to 16 here: pynetdicom's default of 10 refuses the 11th
and 12th association of this load, which is not what is under test (an O-arm sends one series per
association, one at a time: docs/conformance.md).  Every wait polls with a deadline; nothing sleeps.
"""

from __future__ import annotations

import contextlib
import socket
import subprocess
import threading
from pathlib import Path
from typing import Any

import httpx

from tests.faults._service import (
    DEADLINE_S,
    TOKEN,
    ServeProcess,
    free_port,
    mock_controller_process,
    wait_for,
    write_config,
)
from tests.helpers.system_tools import system_tool

N_ASSOCIATIONS = 12
N_IGTL_CLIENTS = 200
SLICES = 16
SIZE_PX = 384
"""12 series x 16 slices of 384 x 384 int16 (~4.7 MB a series, 57 MB in all) decoded as they arrive."""
WINDOW_S = 1.0
AE_TITLE = "OARMREG"
STORESCU = system_tool("storescu")


def _send_pynetdicom(folder: Path, port: int, out: list[list[int]]) -> None:
    from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian
    from pynetdicom import AE

    from dicomnet.scu import associate

    ae = AE(ae_title="OARM_LOAD")
    ae.add_requested_context(CTImageStorage, [ExplicitVRLittleEndian])
    assoc = associate(ae, "127.0.0.1", port, ae_title=AE_TITLE)
    statuses: list[int] = []
    if assoc.is_established:
        try:
            statuses = [
                int(getattr(assoc.send_c_store(p), "Status", -1)) for p in sorted(folder.glob("*.dcm"))
            ]
        finally:
            assoc.release()
    out.append(statuses)


def _deliver_all(folders: list[Path], port: int) -> None:
    """Every folder over its own association, all at the same time; each must be stored whole."""
    if STORESCU is not None:
        procs = [
            subprocess.Popen(
                [STORESCU, "-aet", f"OARM{i:02d}", "-aec", AE_TITLE, "+sd", "127.0.0.1", str(port), str(f)],
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
            )
            for i, f in enumerate(folders)
        ]
        outs = [p.communicate(timeout=DEADLINE_S * 3) for p in procs]
        bad = [(p.returncode, o[-800:]) for p, (o, _) in zip(procs, outs, strict=True) if p.returncode != 0]
        assert not bad, bad
        return
    results: list[list[int]] = []
    threads = [threading.Thread(target=_send_pynetdicom, args=(f, port, results)) for f in folders]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(results) == len(folders) and all(r and set(r) == {0} for r in results), results


def test_still_robot_12_associations_and_200_silent_igtl_clients_every_verdict_still(tmp_path: Path) -> None:
    folders = []
    for i in range(N_ASSOCIATIONS):
        f = tmp_path / "outbox" / f"series{i:02d}"
        _write(f)
        folders.append(f)
    with mock_controller_process() as url:
        cfg, port, dicom_port, igtl_port = tmp_path / "oarmreg.toml", free_port(), free_port(), free_port()
        write_config(cfg, {
            "watch_dir": str(tmp_path / "watch"), "data_dir": str(tmp_path / "data"), "api_token": TOKEN,
            "port": port, "robot.link_url": url, "robot.connect_timeout_s": 2.0,
            "stillness.window_s": WINDOW_S, "stillness.max_gap_s": 0.25,
            "dicom.enabled": True, "dicom.port": dicom_port, "dicom.ae_title": AE_TITLE,
            "dicom.maximum_associations": N_ASSOCIATIONS + 4,
            "dicom.max_associations_per_peer": N_ASSOCIATIONS,  # 12 O-arms played from one address
            "igtl.enabled": True, "igtl.port": igtl_port,
            "igtl.max_clients": N_IGTL_CLIENTS + 8,  # all held (the default 32 refuses the rest)
            "igtl.max_clients_per_address": N_IGTL_CLIENTS + 8,  # from one address (the default: 8)
        })  # fmt: skip
        serve = ServeProcess(cfg, port, tmp_path / "serve.log")
        serve.start()
        try:
            with (
                httpx.Client(base_url=serve.base_url, headers={"Authorization": f"Bearer {TOKEN}"},
                             timeout=DEADLINE_S) as c,
                contextlib.ExitStack() as silent,
            ):  # fmt: skip

                def watched() -> bool:
                    link = c.get("/status").json()["link"]
                    return bool(link["state"] == "connected" and link["history_s"] > WINDOW_S + 0.5)

                wait_for(watched, "the joint history to cover a window")
                for _ in range(N_IGTL_CLIENTS):  # connect and never read
                    s = silent.enter_context(socket.create_connection(("127.0.0.1", igtl_port), timeout=10.0))
                    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
                wait_for(
                    lambda: (
                        c.get("/status").json()["listeners"]["igtl"]["counters"]["connects"] >= N_IGTL_CLIENTS
                    ),
                    "the service to accept the 200 OpenIGTLink clients",
                )
                _deliver_all(folders, dicom_port)

                def recorded() -> list[dict[str, Any]] | None:
                    scans = [s for s in c.get("/scans").json() if s["status"] not in ("receiving",)]
                    return scans if len(scans) >= N_ASSOCIATIONS else None

                scans = wait_for(recorded, "all 12 series recorded")
                st = c.get("/status").json()
            assert sorted(s["status"] for s in scans) == ["complete"] * N_ASSOCIATIONS, [
                (s["id"], s["status"], s["reason"]) for s in scans
            ]
            verdicts = [(s["id"], s["joints"]["verdict"], s["joints"]["stillness_reason"]) for s in scans]
            assert all(v == "still" for _, v, _ in verdicts), verdicts
            assert st["link"]["state"] == "connected", st["link"]
            assert st["listeners"]["dicom"]["counters"], st["listeners"]["dicom"]
        finally:
            serve.stop()


def _write(folder: Path) -> None:
    from tests.helpers.dicom_factory import ramp_volume, write_series

    vol = ramp_volume(SLICES, SIZE_PX, SIZE_PX)
    write_series(folder, vol)
