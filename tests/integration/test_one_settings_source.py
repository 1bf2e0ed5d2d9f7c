"""Issue #35, one home per setting: the DICOM Storage SCP and the OpenIGTLink server are configured
only from ``service/settings.py`` (no second config class re-declaring its defaults and checks), and
a value set in the TOML reaches the running listener, observed over loopback."""

from __future__ import annotations

import asyncio
import importlib
from pathlib import Path

import numpy as np
import pytest
from polling import poll_until, wait_until
from pynetdicom import AE
from pynetdicom.sop_class import Verification  # type: ignore[attr-defined]

from service.intake.storage_scp import StorageScp
from service.navigation.igtl.server import IgtlServer, IgtlStateSource, RegistrationState
from service.settings import load_settings


@pytest.mark.parametrize(
    ("module", "name"),
    [
        ("service.intake.storage_scp", "DicomScpConfig"),
        ("service.navigation.igtl.server", "IgtlServerConfig"),
    ],
)
def test_no_second_config_class(module: str, name: str) -> None:
    assert not hasattr(importlib.import_module(module), name)


def toml(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "oarmreg.toml"
    path.write_text(text, encoding="utf-8")
    return path


def test_igtl_max_clients_from_the_toml_bounds_the_running_server(tmp_path: Path) -> None:
    settings = load_settings(toml(tmp_path, "[igtl]\nport = 0\nmax_clients = 1\n"))
    source = IgtlStateSource(lambda: RegistrationState(None), lambda: None, lambda q: np.eye(4))

    async def main() -> None:
        server = IgtlServer(settings.igtl, source)
        await server.start()
        try:
            _, first = await asyncio.open_connection("127.0.0.1", server.port)
            await wait_until(lambda: server.client_count == 1, "the first client held")
            reader, second = await asyncio.open_connection("127.0.0.1", server.port)
            await wait_until(lambda: server.counters["refused_full"] == 1, "the second client refused")
            assert await asyncio.wait_for(reader.read(), 5.0) == b""  # closed at once, nothing sent
            assert server.client_count == 1
            for w in (first, second):
                w.close()
        finally:
            await server.stop()

    asyncio.run(main())


def test_dicom_maximum_associations_from_the_toml_bounds_the_running_scp(tmp_path: Path) -> None:
    path = toml(tmp_path, '[dicom]\nport = 0\nae_title = "FROMTOML"\nmaximum_associations = 1\n')
    settings = load_settings(path)
    with StorageScp(settings.dicom, tmp_path / "intake") as scp:
        ae = AE(ae_title="OARM")
        ae.add_requested_context(Verification)
        held = ae.associate("127.0.0.1", scp.port, ae_title="FROMTOML")
        try:
            assert held.is_established
            poll_until(lambda: scp.active_associations == 1, "the first association held", 5.0)
            refused = ae.associate("127.0.0.1", scp.port, ae_title="FROMTOML")
            assert refused.is_rejected
            assert scp.counters["rejected_busy"] == 1
        finally:
            held.release()
