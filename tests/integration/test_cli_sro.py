"""``oarmreg register DICOM_DIR --sro OUT.dcm``: the Spatial Registration object from the CLI (issue #12)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pydicom
import pytest

from registration.io.points import write_json
from registration.model.frames import apply, transform_from_xyz_rpy
from service.cli.main import main
from tests.helpers.scan_cache import simulated_scan

IMAGE_FROM_PHANTOM = transform_from_xyz_rpy([2.0, -3.0, 1.0], [10.0, -6.0, 20.0])
ROBOT_FROM_PHANTOM = transform_from_xyz_rpy([500.0, 40.0, 300.0], [0.0, 0.0, 30.0])


@pytest.fixture(scope="module")
def scan_dir(tmp_path_factory: pytest.TempPathFactory, phantom: Any) -> Path:
    from mocks.oarm.dicom_export import write_dicom_series
    from mocks.oarm.simulator import AcquisitionSettings

    out = tmp_path_factory.mktemp("cli-sro") / "scan"
    write_dicom_series(simulated_scan(phantom, IMAGE_FROM_PHANTOM, AcquisitionSettings.preset("small")), out)
    return out


def _robot_points(tmp_path: Path, phantom: Any) -> Path:
    p = tmp_path / "robot.json"
    write_json(p, {"spheres_mm": apply(ROBOT_FROM_PHANTOM, phantom.centres_phantom_mm).tolist()})
    return p


def test_register_writes_an_sro_with_the_stored_robot_frame_uid(
    scan_dir: Path, phantom: Any, tmp_path: Path
) -> None:
    from registration.io.sro import image_from_robot_of
    from service.registrations.robot_frame import robot_frame_uid

    data, sro, js = tmp_path / "data", tmp_path / "reg.dcm", tmp_path / "reg.json"
    argv = [
        "register",
        str(scan_dir),
        "--robot-points",
        str(_robot_points(tmp_path, phantom)),
        "--json",
        str(js),
    ]
    assert main([*argv, "--sro", str(sro), "--data", str(data)]) == 0
    uid = robot_frame_uid(data)  # minted by the first run, reused after
    ds = pydicom.dcmread(sro)
    assert ds.Modality == "REG" and ds.SOPClassUID == "1.2.840.10008.5.1.4.1.1.66.1"
    import json

    m_cli = np.asarray(json.loads(js.read_text())["image_from_robot"])
    np.testing.assert_allclose(image_from_robot_of(ds, uid), m_cli, atol=1e-9)
    truth = IMAGE_FROM_PHANTOM @ np.linalg.inv(ROBOT_FROM_PHANTOM)
    assert np.abs(m_cli[:3, 3] - truth[:3, 3]).max() < 0.5
    n_files = len(list(scan_dir.glob("*.dcm")))
    assert len(ds.ReferencedSeriesSequence[0].ReferencedInstanceSequence) == n_files
    # an explicit UID wins; a malformed one is refused with a non-zero exit and no file
    assert main([*argv, "--sro", str(sro), "--robot-frame-uid", "1.2.826.0.1.99"]) == 0
    image_from_robot_of(pydicom.dcmread(sro), "1.2.826.0.1.99")
    bad = tmp_path / "bad.dcm"
    assert main([*argv, "--sro", str(bad), "--robot-frame-uid", "01.x"]) != 0
    assert not bad.exists()


def test_register_reads_detection_from_the_toml_and_the_flag_overrides_it(
    scan_dir: Path, phantom: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Issue #35: ``register --config`` takes ``[detection] method`` as the service does (the steel
    phantom's own estimator is ``rays``); ``--method`` overrides the file."""
    import json

    monkeypatch.delenv("OARMREG_DETECTION__METHOD", raising=False)
    toml, js = tmp_path / "oarmreg.toml", tmp_path / "reg.json"
    toml.write_text('[detection]\nmethod = "subvoxel"\n', encoding="utf-8")
    argv = ["register", str(scan_dir), "--robot-points", str(_robot_points(tmp_path, phantom))]
    argv += ["--json", str(js), "--config", str(toml)]
    for extra, want in (([], "subvoxel"), (["--method", "core"], "core")):
        assert main([*argv, *extra]) == 0
        assert json.loads(js.read_text())["provenance"]["detection_method"] == want
