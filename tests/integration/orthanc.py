"""Orthanc (Debian's ``orthanc`` package) as a real PACS peer for the tests (issue #23).

:func:`running_orthanc` starts ``Orthanc config.json`` with its own configuration, storage and
index in a temp folder, HTTP and DICOM on free ports; REST only from localhost
(``RemoteAccessAllowed: false``).  Orthanc 1.10 has no option to bind its DICOM port to loopback,
so it accepts C-STORE only from modalities it knows by AE title *and* host 127.0.0.1
(``DicomAlwaysAllowStore: false``, ``DicomCheckModalityHost: true``).  A Lua
``ReceivedInstanceFilter`` raises for REG instances while the file ``refuse-reg`` exists in its
folder (:meth:`Orthanc.refuse_reg`); Orthanc then answers the C-STORE with 0xA700: the PACS
refuses on demand.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import socket
import subprocess
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx

from tests.integration.polling import poll_until

ORTHANC = shutil.which("Orthanc") or ("/usr/sbin/Orthanc" if Path("/usr/sbin/Orthanc").is_file() else None)
AE_TITLE = "ORTHANC"
START_TIMEOUT_S = 30.0
FILTER_LUA = """
function ReceivedInstanceFilter(dicom, origin, info)
  local flag = io.open('REFUSE_FLAG', 'r')
  if flag ~= nil and dicom.Modality == 'REG' then
    flag:close()
    error('REG refused by the test')
  end
  if flag ~= nil then flag:close() end
  return true
end
"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class Orthanc:
    http: httpx.Client
    dicom_port: int
    http_port: int
    log: Path
    root: Path

    def add_modality(self, name: str, ae_title: str, port: int) -> None:
        r = self.http.put(f"/modalities/{name}", json={"AET": ae_title, "Host": "127.0.0.1", "Port": port})
        r.raise_for_status()

    def refuse_reg(self, refuse: bool) -> None:
        flag = self.root / "refuse-reg"
        if refuse:
            flag.touch()
        else:
            flag.unlink(missing_ok=True)

    def upload(self, files: list[Path]) -> str:
        """POST each file to /instances; the Orthanc id of their series."""
        series = set()
        for f in files:
            r = self.http.post("/instances", content=f.read_bytes())
            r.raise_for_status()
            series.add(r.json()["ParentSeries"])
        assert len(series) == 1, series
        return series.pop()

    def find_instance(self, sop_instance_uid: str) -> str | None:
        r = self.http.post(
            "/tools/find", json={"Level": "Instance", "Query": {"SOPInstanceUID": sop_instance_uid}}
        )
        r.raise_for_status()
        ids = r.json()
        return str(ids[0]) if ids else None

    def get(self, path: str) -> Any:
        r = self.http.get(path)
        r.raise_for_status()
        return r.json()


@contextlib.contextmanager
def running_orthanc(
    root: Path, *, modalities: dict[str, list[Any]] | None = None, tls: tuple[Path, Path, Path] | None = None
) -> Iterator[Orthanc]:
    """Orthanc on free loopback ports with its data in ``root`` (stopped and reaped on exit).

    ``tls`` = (certificate, private key, trusted CA certificates): its DICOM port speaks only
    DICOM TLS (Orthanc ≥ 1.9; client certificates not required)."""
    assert ORTHANC is not None
    root.mkdir(parents=True, exist_ok=True)
    http_port, dicom_port = free_port(), free_port()
    (root / "filter.lua").write_text(FILTER_LUA.replace("REFUSE_FLAG", str(root / "refuse-reg")))
    config = {
        "Name": "oarmreg-test-pacs",
        "StorageDirectory": str(root / "storage"),
        "IndexDirectory": str(root / "index"),
        "HttpPort": http_port,
        "DicomPort": dicom_port,
        "DicomAet": AE_TITLE,
        "RemoteAccessAllowed": False,
        "AuthenticationEnabled": False,
        "DicomAlwaysAllowStore": False,
        "DicomCheckModalityHost": True,
        "DicomCheckCalledAet": True,
        "DicomModalities": modalities or {},
        "Plugins": [],
        "LuaScripts": [str(root / "filter.lua")],
        "HttpsCACertificates": "",
    }
    if tls is not None:
        cert, key, trusted = tls
        config |= {
            "DicomTlsEnabled": True,
            "DicomTlsCertificate": str(cert),
            "DicomTlsPrivateKey": str(key),
            "DicomTlsTrustedCertificates": str(trusted),
            "DicomTlsRemoteCertificateRequired": False,
        }
    cfg = root / "orthanc.json"
    cfg.write_text(json.dumps(config, indent=2))
    log = root / "orthanc.log"
    with log.open("ab") as out:
        proc = subprocess.Popen([ORTHANC, str(cfg)], cwd=root, stdout=out, stderr=subprocess.STDOUT)
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{http_port}", timeout=30.0) as http:

            def up() -> bool:
                if proc.poll() is not None:
                    raise AssertionError(f"Orthanc exited with {proc.returncode}:\n{log.read_text()[-3000:]}")
                try:
                    return http.get("/system").status_code == 200
                except httpx.HTTPError:
                    return False

            poll_until(up, "Orthanc to answer /system", START_TIMEOUT_S, interval_s=0.05)
            yield Orthanc(http, dicom_port, http_port, log, root)
    finally:
        proc.terminate()
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(30)
