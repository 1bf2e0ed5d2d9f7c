"""The Spatial Registration object passes dicom3tools' dciodvfy with no errors."""

from __future__ import annotations

import shutil
import subprocess
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest
from pydicom.dataset import Dataset
from pydicom.uid import CTImageStorage, generate_uid

from registration.io.sro import build_spatial_registration

DCIODVFY = shutil.which("dciodvfy")


@pytest.mark.skipif(DCIODVFY is None, reason="dicom3tools dciodvfy not installed")
def test_sro_has_no_dciodvfy_errors(tmp_path: Path) -> None:
    ct = []
    for i in range(4):
        d = Dataset()
        d.SOPClassUID, d.SOPInstanceUID = CTImageStorage, generate_uid()
        d.StudyInstanceUID, d.SeriesInstanceUID, d.FrameOfReferenceUID = "1.2.3", "1.2.3.4", "1.2.3.5"
        d.PatientName, d.PatientID, d.PatientBirthDate, d.PatientSex = "PHANTOM^CUBE", "P1", "", "O"
        d.StudyDate, d.StudyTime, d.StudyID, d.AccessionNumber = "20260304", "050000", "1", ""
        d.ReferringPhysicianName, d.Laterality, d.InstanceNumber = "", "", i + 1
        ct.append(d)
    m = np.eye(4)
    m[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    m[:3, 3] = [-412.25, 233.5, -80.125]
    ds = build_spatial_registration(
        m, ct, robot_frame_of_reference_uid=generate_uid(), fre_mm=0.41, status="current",
        registration_id="reg-7", content_datetime=datetime(2026, 3, 4, 5, 6, 7), tre_pred_mm=0.8,
        software_version="0.1.0",
    )  # fmt: skip
    path = tmp_path / "sro.dcm"
    ds.save_as(path, enforce_file_format=True)
    r = subprocess.run([DCIODVFY, str(path)], capture_output=True, text=True, timeout=60)
    out = r.stdout + r.stderr
    print(out)
    errors = [line for line in out.splitlines() if line.startswith("Error")]
    assert "SpatialRegistration" in out or "Spatial Registration" in out, out
    assert errors == [], "\n".join(errors)
