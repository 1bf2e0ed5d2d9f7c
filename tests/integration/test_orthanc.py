"""Orthanc as a real PACS on both sides of the DICOM link (issue #23).

One Orthanc (``tests/integration/orthanc.py``) and one service per module.  Orthanc forwards a
simulated series to the service's Storage SCP (``POST /modalities/oarmreg/store``, its own C-STORE
SCU); the scan is recorded, auto-registered, and the registration's Spatial Registration object is
archived back to Orthanc by C-STORE (``[pacs]``).  Orthanc's REST API then says where it landed.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import pydicom
import pytest

from service.events import DicomAssociationReleased, PacsExportFailed
from tests.integration.orthanc import AE_TITLE as ORTHANC_AET
from tests.integration.orthanc import ORTHANC, Orthanc, running_orthanc
from tests.integration.peer_service import (
    AE_TITLE,
    PeerService,
    running_service,
    simulated_series,
    wait_export,
)

pytestmark = pytest.mark.skipif(ORTHANC is None, reason="Orthanc not installed (.ci/run installs it)")

CALLING_AET = "OARMREG_SCU"


@dataclass
class Setup:
    orthanc: Orthanc
    svc: PeerService
    series_uid: str
    study_uid: str
    orthanc_series: str
    scan: dict[str, Any]
    registration: dict[str, Any]


def export_of(svc: PeerService, registration_id: int, state: str) -> dict[str, Any]:
    return wait_export(svc, registration_id, lambda e: bool(e["state"] == state), state)


@pytest.fixture(scope="module")
def setup(tmp_path_factory: pytest.TempPathFactory, phantom: Any) -> Iterator[Setup]:
    root = tmp_path_factory.mktemp("orthanc")
    # the series as an O-arm would have sent it to the PACS
    series_uid, files = simulated_series(phantom, root / "outbox")
    study_uid = str(pydicom.dcmread(files[0], stop_before_pixels=True).StudyInstanceUID)
    with running_orthanc(root / "orthanc") as orthanc:
        orthanc.add_modality("oarmreg-scu", CALLING_AET, 1)  # our SCU: may store (host checked)
        pacs = {
            "pacs.host": "127.0.0.1",
            "pacs.port": orthanc.dicom_port,
            "pacs.ae_title": ORTHANC_AET,
            "pacs.calling_ae_title": CALLING_AET,
            "pacs.retry_initial_s": 0.2,
            "pacs.retry_max_s": 1.0,
        }
        with running_service(root / "svc", phantom, **pacs) as svc:
            orthanc.add_modality("oarmreg", AE_TITLE, svc.dicom_port)
            orthanc_series = orthanc.upload(files)
            r = orthanc.http.post(
                "/modalities/oarmreg/store", json={"Resources": [orthanc_series], "Synchronous": True}
            )
            assert r.status_code == 200, r.text
            scan = svc.wait_scan(series_uid)
            reg = svc.wait_registration(scan["id"])
            yield Setup(orthanc, svc, series_uid, study_uid, orthanc_series, scan, reg)


def test_orthanc_forwarded_series_is_recorded_complete_and_registers(setup: Setup) -> None:
    scan, reg = setup.scan, setup.registration
    n_orthanc = len(setup.orthanc.get(f"/series/{setup.orthanc_series}")["Instances"])
    assert scan["status"] == "complete" and scan["n_slices"] == n_orthanc
    released = [e for e in setup.svc.events(DicomAssociationReleased) if e.series_uid == setup.series_uid]
    assert released and released[0].calling_ae == ORTHANC_AET and released[0].outcome == "complete"
    assert reg["status"] == "accepted" and reg["n_matched"] == reg["n_expected"]


def test_registration_archived_in_the_scans_study_referencing_its_series(setup: Setup) -> None:
    reg = setup.registration
    exp = export_of(setup.svc, reg["id"], "sent")
    assert exp["dimse_status"] == 0 and exp["attempts"] >= 1
    assert exp["destination"] == f"{ORTHANC_AET}@127.0.0.1:{setup.orthanc.dicom_port}"
    oid = setup.orthanc.find_instance(exp["sop_instance_uid"])
    assert oid is not None, "the REG instance is not in Orthanc"
    tags = setup.orthanc.get(f"/instances/{oid}/tags?simplify")
    assert tags["Modality"] == "REG" and tags["SOPClassUID"] == "1.2.840.10008.5.1.4.1.1.66.1"
    assert tags["StudyInstanceUID"] == setup.study_uid
    # in the same Orthanc study as the CT series it registers
    ct_study = setup.orthanc.get(f"/series/{setup.orthanc_series}")["ParentStudy"]
    assert setup.orthanc.get(f"/instances/{oid}/study")["ID"] == ct_study
    refs = tags["ReferencedSeriesSequence"]
    assert [r["SeriesInstanceUID"] for r in refs] == [setup.series_uid]
    ct_sops = {setup.orthanc.get(f"/instances/{i}/tags?simplify")["SOPInstanceUID"]
               for i in setup.orthanc.get(f"/series/{setup.orthanc_series}")["Instances"]}  # fmt: skip
    assert {r["ReferencedSOPInstanceUID"] for r in refs[0]["ReferencedInstanceSequence"]} == ct_sops
    # the matrix the PACS holds is the served one, in the REG object's convention (docs/slicer.md,
    # "one convention": the robot frame declared as the controller's (-x, -y, z))
    robot_item = tags["RegistrationSequence"][1]
    m = robot_item["MatrixRegistrationSequence"][0]["MatrixSequence"][0][
        "FrameOfReferenceTransformationMatrix"
    ]
    got = np.asarray([float(v) for v in m.split("\\")]).reshape(4, 4)
    np.testing.assert_allclose(
        got, np.asarray(reg["image_from_robot"]) @ np.diag([-1.0, -1.0, 1.0, 1.0]), atol=1e-6
    )
    audit = setup.svc.client.get("/audit").json()
    assert any(
        a["action"] == "pacs_export" and a["target_id"] == reg["id"] and a["outcome"] == "sent" for a in audit
    )


def test_pacs_out_of_resources_is_retried_and_archived_once_the_pacs_takes_it(setup: Setup) -> None:
    """Orthanc's refusal is 0xA700 (Refused: Out of Resources, PS3.4 B.2.3), a transient status
    (issue 32): the export is retried with the queue's backoff, never marked failed, the registration
    stays accepted and current, and once the PACS takes objects again the queue archives it by itself."""
    svc = setup.svc
    setup.orthanc.refuse_reg(True)
    try:
        r = svc.client.post("/register", json={"scan_id": setup.scan["id"]})
        assert r.status_code == 200, r.text
        reg = r.json()
        retried = wait_export(
            svc, reg["id"], lambda e: e["state"] == "pending" and e["attempts"] >= 2, "retried after 0xA700"
        )
        assert setup.orthanc.find_instance(retried["sop_instance_uid"]) is None
    finally:
        setup.orthanc.refuse_reg(False)
    assert retried["dimse_status"] == 0xA700 and "0xA700" in retried["reason"], retried
    assert "transient" in retried["reason"], retried
    after = svc.client.get(f"/registrations/{reg['id']}").json()
    assert after["status"] == "accepted" and after["is_current"]
    assert svc.client.get("/registration/current").json()["id"] == reg["id"]
    sent = export_of(svc, reg["id"], "sent")  # the queue's own retry: nobody asked again
    assert setup.orthanc.find_instance(sent["sop_instance_uid"]) is not None
    assert not [e for e in svc.events(PacsExportFailed) if e.registration_id == reg["id"]]
    r = svc.client.post(f"/registrations/{reg['id']}/pacs-export", json={})  # already archived
    assert r.status_code == 409 and r.headers["content-type"].startswith("application/problem+json")
    assert "already archived" in r.json()["detail"]


def test_retry_endpoint_refuses_what_cannot_be_archived(setup: Setup) -> None:
    r = setup.svc.client.post("/registrations/999999/pacs-export", json={})
    assert r.status_code == 404
