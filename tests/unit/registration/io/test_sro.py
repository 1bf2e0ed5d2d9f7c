"""Spatial Registration object: matrix direction and round trip, references, refusals;
the robot frame UID file."""

from __future__ import annotations

import math
from datetime import datetime
from pathlib import Path

import numpy as np
import pydicom
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydicom.dataset import Dataset
from pydicom.uid import CTImageStorage, generate_uid

from registration.errors import SroError
from registration.io.sro import SPATIAL_REGISTRATION_STORAGE, build_spatial_registration, image_from_robot_of
from service.errors import RobotFrameUidError
from service.registrations.robot_frame import robot_frame_uid

ROBOT_FOR = "1.2.826.0.1.3680043.8.498.1"
WHEN = datetime(2026, 3, 4, 5, 6, 7, 890000)


def rigid(rx_deg: float, rz_deg: float, t: tuple[float, float, float]) -> np.ndarray:
    a, c = math.radians(rx_deg), math.radians(rz_deg)
    rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    rz = np.array([[math.cos(c), -math.sin(c), 0], [math.sin(c), math.cos(c), 0], [0, 0, 1]])
    m = np.eye(4)
    m[:3, :3] = rz @ rx
    m[:3, 3] = t
    return m


IMAGE_FROM_ROBOT = rigid(17.0, -123.0, (-412.123456789, 233.5, -80.125))


def ct_headers(
    n: int = 3, study: str = "1.2.3", series: str = "1.2.3.4", for_uid: str = "1.2.3.5"
) -> list[Dataset]:
    out = []
    for i in range(n):
        d = Dataset()
        d.SOPClassUID, d.SOPInstanceUID = CTImageStorage, generate_uid()
        d.StudyInstanceUID, d.SeriesInstanceUID, d.FrameOfReferenceUID = study, series, for_uid
        d.PatientName, d.PatientID, d.StudyDate, d.StudyTime = "PHANTOM^CUBE", "P1", "20260304", "050000"
        d.InstanceNumber = i + 1
        out.append(d)
    return out


def build(**kw: object) -> Dataset:
    args: dict[str, object] = dict(
        robot_frame_of_reference_uid=ROBOT_FOR, fre_mm=0.4123, status="current",
        registration_id="reg-7", content_datetime=WHEN, tre_pred_mm=0.8,
    )  # fmt: skip
    args.update(kw)
    m = args.pop("m", IMAGE_FROM_ROBOT)
    ct = args.pop("ct", ct_headers())
    return build_spatial_registration(m, ct, **args)  # type: ignore[arg-type]


def test_matrix_round_trips_through_a_file_and_maps_robot_to_image(tmp_path: Path) -> None:
    ds = build()
    ds.save_as(tmp_path / "sro.dcm", enforce_file_format=True)
    back = pydicom.dcmread(tmp_path / "sro.dcm")
    m = image_from_robot_of(back, ROBOT_FOR)
    np.testing.assert_allclose(m, IMAGE_FROM_ROBOT, rtol=0, atol=1e-9)
    # Direction (PS3.3 C.20.2.1.1): the item's matrix maps the item's (robot) RCS into the
    # Registered RCS (the SRO's FrameOfReferenceUID, the scan's).
    p_robot = np.array([10.0, -20.0, 300.0, 1.0])
    np.testing.assert_allclose(m @ p_robot, IMAGE_FROM_ROBOT @ p_robot, atol=1e-8)
    assert back.FrameOfReferenceUID == "1.2.3.5"
    raw = back.RegistrationSequence[1].MatrixRegistrationSequence[0].MatrixSequence[0]
    # row-major: the first four values are the first row of image_from_robot @ diag(-1, -1, 1, 1)
    # (the robot frame's DICOM coordinates are (-x, -y, z), registration/io/sro.py)
    assert [float(v) for v in raw.FrameOfReferenceTransformationMatrix][:4] == pytest.approx(
        list((IMAGE_FROM_ROBOT @ np.diag([-1.0, -1, 1, 1]))[0])
    )


def test_structure_identity_item_references_and_comments() -> None:
    ct = ct_headers()
    ds = build(ct=ct)
    assert ds.SOPClassUID == SPATIAL_REGISTRATION_STORAGE and ds.Modality == "REG"
    scan, robot = ds.RegistrationSequence
    assert scan.FrameOfReferenceUID == "1.2.3.5" and robot.FrameOfReferenceUID == ROBOT_FOR
    np.testing.assert_array_equal(image_from_robot_of(ds, "1.2.3.5"), np.eye(4))
    assert [r.ReferencedSOPInstanceUID for r in scan.ReferencedImageSequence] == [
        d.SOPInstanceUID for d in ct
    ]
    (ser,) = ds.ReferencedSeriesSequence
    assert ser.SeriesInstanceUID == "1.2.3.4" and len(ser.ReferencedInstanceSequence) == 3
    code = robot.MatrixRegistrationSequence[0].RegistrationTypeCodeSequence[0]
    assert (code.CodeValue, code.CodingSchemeDesignator) == ("125022", "DCM")
    assert "FRE 0.412 mm" in robot.MatrixRegistrationSequence[0].FrameOfReferenceTransformationComment
    assert "current" in ds.ContentDescription and (ds.ContentDate, ds.ContentTime) == (
        "20260304",
        "050607.890000",
    )
    assert all(
        len(str(v)) <= 16
        for v in robot.MatrixRegistrationSequence[0].MatrixSequence[0].FrameOfReferenceTransformationMatrix
    )
    assert ds.PatientID == "P1" and ds.StudyInstanceUID == "1.2.3"


def test_non_rigid_matrix_refused() -> None:
    m = IMAGE_FROM_ROBOT.copy()
    m[:3, :3] *= 1.01
    with pytest.raises(SroError, match="not rigid"):
        build(m=m)
    mirrored = IMAGE_FROM_ROBOT @ np.diag([-1.0, 1, 1, 1])
    with pytest.raises(SroError, match="det R"):
        build(m=mirrored)


def test_mixed_or_empty_scan_refused() -> None:
    with pytest.raises(SroError, match="SeriesInstanceUID"):
        build(ct=ct_headers(2) + ct_headers(1, series="1.2.3.9"))
    with pytest.raises(SroError, match="no CT instances"):
        build(ct=[])


def test_robot_frame_uid_minted_once_and_kept(tmp_path: Path) -> None:
    uid = robot_frame_uid(tmp_path / "data")
    assert uid == robot_frame_uid(tmp_path / "data")
    assert (tmp_path / "data" / "robot_frame_of_reference_uid.txt").read_text().strip() == uid
    assert [p.name for p in (tmp_path / "data").iterdir()] == ["robot_frame_of_reference_uid.txt"]
    assert robot_frame_uid(tmp_path / "other") != uid


def test_robot_frame_uid_file_corrupt_is_an_error(tmp_path: Path) -> None:
    (tmp_path / "robot_frame_of_reference_uid.txt").write_text("not a uid")
    with pytest.raises(RobotFrameUidError, match="not a DICOM UID"):
        robot_frame_uid(tmp_path)


rotations = st.tuples(*[st.floats(-180.0, 180.0, allow_nan=False)] * 3)
translations = st.tuples(*[st.floats(-1500.0, 1500.0, allow_nan=False)] * 3)


@settings(max_examples=15, deadline=None)
@given(rpy=rotations, xyz=translations, p_robot=translations)
def test_slicerrt_reads_the_same_transform_as_igtl_robot_to_image(
    rpy: tuple[float, float, float], xyz: tuple[float, float, float], p_robot: tuple[float, float, float]
) -> None:
    """Issue 31 item 5: read as SlicerRT reads it (LPS->RAS on both sides of the matrix), the REG
    object places a robot point where OpenIGTLink's ``RobotToImage`` does; the old REG (the matrix
    ``image_from_robot`` as is) put it up to 2·|(x, y)| away (825 mm in the report)."""
    from registration.model.frames import transform_from_xyz_rpy
    from service.navigation.igtl.server import RAS_FROM_LPS
    from tests.helpers.slicerrt_sro import slicerrt_transform_to_parent

    image_from_robot = transform_from_xyz_rpy(list(xyz), list(rpy))
    ds = build(m=image_from_robot)
    # the server's RobotToImage conversion (docs/slicer.md §2); the matrix it sends is read with pyigtl
    # in tests/integration/test_or_integration.py::test_reg_read_as_slicerrt_equals_robot_to_image
    robot_to_image = RAS_FROM_LPS @ image_from_robot
    slicer = slicerrt_transform_to_parent(ds)
    p = np.array([*p_robot, 1.0])
    np.testing.assert_allclose(slicer @ p, robot_to_image @ p, rtol=0, atol=1e-6)
    # and a strict DICOM reader: the robot point in the REG's declared (-x, -y, z) coordinates lands
    # at the LPS point REST's image_from_robot gives
    raw = ds.RegistrationSequence[1].MatrixRegistrationSequence[0].MatrixSequence[0]
    m = np.asarray([float(v) for v in raw.FrameOfReferenceTransformationMatrix]).reshape(4, 4)
    np.testing.assert_allclose(m @ (np.diag([-1.0, -1, 1, 1]) @ p), image_from_robot @ p, atol=1e-6)
    np.testing.assert_allclose(image_from_robot_of(ds, ROBOT_FOR), image_from_robot, atol=1e-9)


def test_archived_reg_is_read_in_its_own_convention() -> None:
    """A REG written before the convention (comment 'image_from_robot LPS mm…') holds
    image_from_robot itself; image_from_robot_of reads it as such."""
    ds = build()
    mreg = ds.RegistrationSequence[1].MatrixRegistrationSequence[0]
    mreg.MatrixSequence[0].FrameOfReferenceTransformationMatrix = [
        f"{v:.12g}" for v in IMAGE_FROM_ROBOT.reshape(16)
    ]
    mreg.FrameOfReferenceTransformationComment = "image_from_robot LPS mm; FRE 0.412 mm; current"
    np.testing.assert_allclose(image_from_robot_of(ds, ROBOT_FOR), IMAGE_FROM_ROBOT, atol=1e-9)
