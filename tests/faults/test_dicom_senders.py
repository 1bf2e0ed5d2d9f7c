"""Fault suite, issue 41 item 6: only known DICOM senders store, and no sender can hold the O-arm out.

One real service (``python -m service.cli serve``) with the DICOM SCP on; the peers are dcmtk's
``storescu`` / ``echoscu`` (processes of their own) and pynetdicom associations bound to chosen
loopback addresses (127.0.0.0/8 is all loopback on Linux):

* a calling AE title not in ``dicom.allowed_calling_ae_titles`` is refused at association
  (A-ASSOCIATE-RJ) and nothing it sends is stored; an entry ``TITLE@ADDRESS`` admits that title from
  that address only; ``/status`` lists the allow-list;
* an association that only echoes is aborted after ``dicom.network_timeout_s`` without a C-STORE;
* one address holds at most ``dicom.max_associations_per_peer`` associations; another still gets in;
* with the allow-list empty the SCP says so at start-up and on ``/status``.

Every wait polls with a deadline; nothing sleeps.
"""

from __future__ import annotations

import logging
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.faults._service import (
    DEADLINE_S,
    TOKEN,
    ServeProcess,
    factory_series,
    free_port,
    served,
    wait_for,
    write_config,
)
from tests.helpers.system_tools import system_tool

STORESCU = system_tool("storescu")
ECHOSCU = system_tool("echoscu")
pytestmark = pytest.mark.skipif(STORESCU is None or ECHOSCU is None, reason="dcmtk not installed")

AE_TITLE = "OARMREG"
OARM = "OARM_SIM"
"""The mock O-arm's calling AE title (``mocks/oarm/cstore.py``)."""
TIED = "SCANNER"
TIED_ADDRESS = "127.0.46.3"
NETWORK_TIMEOUT_S = 2.0
PER_PEER = 2
ALLOWED = [OARM, f"{TIED}@{TIED_ADDRESS}"]


@dataclass
class Scp:
    serve: ServeProcess
    client: httpx.Client
    port: int
    intake: Path

    def dicom(self) -> dict[str, Any]:
        return dict(self.client.get("/status").json()["listeners"]["dicom"])

    def stored_files(self) -> list[Path]:
        return sorted(self.intake.rglob("*.dcm")) if self.intake.exists() else []


@pytest.fixture(scope="module")
def scp(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Scp]:
    from service.settings import DicomSettings

    root = tmp_path_factory.mktemp("senders")
    cfg, port, dicom_port = root / "oarmreg.toml", free_port(), free_port()
    known = DicomSettings.model_fields
    write_config(cfg, {
        "watch_dir": str(root / "watch"), "data_dir": str(root / "data"), "api_token": TOKEN, "port": port,
        "robot.link_url": f"simple-message://127.0.0.1:{free_port()}", "robot.connect_timeout_s": 1.0,
        "dicom.enabled": True, "dicom.port": dicom_port, "dicom.ae_title": AE_TITLE,
        "dicom.network_timeout_s": NETWORK_TIMEOUT_S,
        **({"dicom.max_associations_per_peer": PER_PEER} if "max_associations_per_peer" in known else {}),
    })  # fmt: skip
    with cfg.open("a", encoding="utf-8") as f:  # [dicom] is the last table; write_config has no lists
        f.write("allowed_calling_ae_titles = [" + ", ".join(f'"{a}"' for a in ALLOWED) + "]\n")
    with served(cfg, port) as (serve, client):
        yield Scp(serve, client, dicom_port, root / "data" / "dicom-intake")


def _associate(scp: Scp, calling: str, source: str = "127.0.0.1") -> Any:
    from pynetdicom import AE

    from dicomnet.scu import associate

    ae = AE(ae_title=calling)
    ae.add_requested_context("1.2.840.10008.1.1")  # Verification
    return associate(ae, "127.0.0.1", scp.port, ae_title=AE_TITLE, bind_address=(source, 0))


def test_item6_an_unknown_sender_is_refused_at_association_and_stores_nothing(
    scp: Scp, tmp_path: Path
) -> None:
    """``storescu -aet ANYONE`` with a CT instance: A-ASSOCIATE-RJ, nothing stored (the issue: one such
    instance in the current series withdrew the registration); the mock O-arm's title is echoed."""
    files = factory_series(tmp_path / "ct", n=1)
    r = subprocess.run([str(STORESCU), "-aet", "ANYONE", "-aec", AE_TITLE, "127.0.0.1", str(scp.port),
                        *map(str, files)], capture_output=True, text=True, timeout=DEADLINE_S)  # fmt: skip
    assert r.returncode != 0 and "reject" in (r.stdout + r.stderr).lower(), r.stdout + r.stderr
    assert scp.stored_files() == []
    ok = subprocess.run([str(ECHOSCU), "-aet", OARM, "-aec", AE_TITLE, "127.0.0.1", str(scp.port)],
                        capture_output=True, text=True, timeout=DEADLINE_S)  # fmt: skip
    assert ok.returncode == 0, ok.stderr
    assert scp.dicom()["allowed_callers"] == ALLOWED


def test_item6_a_title_tied_to_an_address_is_admitted_from_there_only(scp: Scp) -> None:
    elsewhere = _associate(scp, TIED, "127.0.0.1")
    assert not elsewhere.is_established
    there = _associate(scp, TIED, TIED_ADDRESS)
    try:
        assert there.is_established
    finally:
        there.release()


def test_item6_an_association_that_only_echoes_is_closed(scp: Scp) -> None:
    """``echoscu --repeat`` many echoes on one association: aborted after ``network_timeout_s`` without
    a C-STORE (before: ten such associations held the O-arm out indefinitely)."""
    before = scp.dicom()["counters"].get("closed_echo_only", 0)
    started = time.monotonic()
    r = subprocess.run([str(ECHOSCU), "--repeat", "10000000", "-aet", OARM, "-aec", AE_TITLE,
                        "127.0.0.1", str(scp.port)], capture_output=True, text=True,
                       timeout=NETWORK_TIMEOUT_S + 20)  # fmt: skip
    # echoscu exits 0 or 1 when the peer aborts (it says so on stderr); every echo answered = not closed
    assert r.returncode != 0 or "aborted" in r.stderr.lower(), (r.returncode, r.stderr)
    assert time.monotonic() - started >= NETWORK_TIMEOUT_S
    assert scp.dicom()["counters"]["closed_echo_only"] == before + 1


def test_item6_one_address_cannot_take_every_slot(scp: Scp) -> None:
    """``PER_PEER`` associations from 127.0.0.1: the next from there is refused (a named problem on
    ``/status``), while another address still gets one of the ``maximum_associations`` slots."""
    held = [_associate(scp, OARM) for _ in range(PER_PEER)]
    try:
        assert all(a.is_established for a in held)
        extra = _associate(scp, OARM)
        assert not extra.is_established, "one address took more than its share of the slots"
        wait_for(
            lambda: any(
                "max_associations_per_peer" in p for p in scp.client.get("/status").json()["problems"]
            ),
            "the refusal named on /status",
        )
        other = _associate(scp, TIED, TIED_ADDRESS)
        try:
            assert other.is_established
        finally:
            other.release()
    finally:
        for a in held:
            a.release()


def test_item6_an_empty_allow_list_is_said_at_start_up_and_on_status(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    from service.intake.storage_scp import StorageScp
    from service.settings import DicomSettings

    config = DicomSettings(enabled=True, port=0)
    with (
        caplog.at_level(logging.WARNING, logger="service.intake.storage_scp"),
        StorageScp(config, tmp_path) as s,
    ):
        assert "allowed_calling_ae_titles is empty" in str(getattr(s, "allow_list", ""))
    assert any("allowed_calling_ae_titles is empty" in r.getMessage() for r in caplog.records)
