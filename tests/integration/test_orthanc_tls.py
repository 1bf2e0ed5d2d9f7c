"""Archiving to a PACS that offers DICOM TLS: Orthanc with TLS on its DICOM port (issue "speak with
the reference implementations": ``[pacs]`` TLS when the PACS offers it).

With ``pacs.tls_ca_file`` naming the CA that signed Orthanc's certificate the registration's
Spatial Registration object arrives over TLS; without it the plain association to the TLS-only
port fails and the export says so (``failed`` or still ``pending`` with a reason), the registration
staying accepted.
"""

from __future__ import annotations

import io
import shutil
from pathlib import Path
from typing import Any

import pydicom
import pytest

from tests.integration.orthanc import AE_TITLE as ORTHANC_AET
from tests.integration.orthanc import ORTHANC, running_orthanc
from tests.integration.peer_service import running_service, send_files, simulated_series, wait_export
from tests.integration.test_or_integration import make_tls

pytestmark = pytest.mark.skipif(
    ORTHANC is None or shutil.which("openssl") is None, reason="Orthanc / openssl not installed (.ci/run)"
)
CALLING_AET = "OARMREG_SCU"


def test_registration_archived_over_dicom_tls_and_refused_in_plain(tmp_path: Path, phantom: Any) -> None:
    (tmp_path / "pki").mkdir()
    ca, cert, key = make_tls(tmp_path / "pki")
    series_uid, files = simulated_series(phantom, tmp_path / "outbox")
    with running_orthanc(tmp_path / "orthanc", tls=(cert, key, ca)) as orthanc:
        orthanc.add_modality("oarmreg-scu", CALLING_AET, 1)
        pacs = {
            "pacs.host": "127.0.0.1", "pacs.port": orthanc.dicom_port, "pacs.ae_title": ORTHANC_AET,
            "pacs.calling_ae_title": CALLING_AET, "pacs.retry_initial_s": 0.2, "pacs.retry_max_s": 1.0,
        }  # fmt: skip
        with running_service(tmp_path / "tls", phantom, **pacs, **{"pacs.tls_ca_file": ca}) as svc:
            send_files(svc.dicom_port, files)
            reg = svc.wait_registration(svc.wait_scan(series_uid)["id"])
            exp = wait_export(svc, reg["id"], lambda e: bool(e["state"] == "sent"), "sent")
            assert exp["destination"].endswith("+tls"), exp
            instance = orthanc.find_instance(exp["sop_instance_uid"])
            assert instance is not None
            ds = pydicom.dcmread(io.BytesIO(orthanc.http.get(f"/instances/{instance}/file").content))
            assert ds.Modality == "REG" and ds.SOPInstanceUID == exp["sop_instance_uid"]

        with running_service(tmp_path / "plain", phantom, **pacs) as svc:
            send_files(svc.dicom_port, files)
            reg = svc.wait_registration(svc.wait_scan(series_uid)["id"])
            exp = wait_export(
                svc,
                reg["id"],
                lambda e: bool(e["attempts"] >= 1 and e["state"] != "sent"),
                "tried and not sent",
            )
            assert exp["reason"], exp  # says why: no association with the TLS-only port
            assert svc.client.get(f"/registrations/{reg['id']}").json()["status"] == "accepted"
