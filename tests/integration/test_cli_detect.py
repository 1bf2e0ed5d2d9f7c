"""``oarmreg detect`` end to end on a simulated DICOM export (issue #3 item 6)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from mocks.oarm.dicom_export import write_dicom_series
from mocks.oarm.simulator import AcquisitionSettings, demo_pose
from service.cli.main import main
from service.error_map import EXIT_INPUT
from tests.helpers.scan_cache import simulated_scan

MATCH_MM = 0.5
"""A detection within this of a truth centre is that sphere (spheres are ≥ 15 mm apart)."""


@pytest.fixture(scope="module")
def export(tmp_path_factory: pytest.TempPathFactory, phantom):  # type: ignore[no-untyped-def]
    settings = AcquisitionSettings.preset("demo", rows=256, columns=256, n_views=180)
    scan = simulated_scan(phantom, demo_pose(), settings)
    out = tmp_path_factory.mktemp("cli-detect") / "series"
    write_dicom_series(scan, out, reverse_order=True)
    return out, scan


def test_detect_writes_the_documented_json(export, tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    folder, scan = export
    out = tmp_path / "det.json"
    assert main(["detect", str(folder), "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "sphere(s)" in text and f"wrote {out}" in text
    assert "nan" not in text  # unmeasured radius / slices / score print as "-" (issue 34)
    assert not [ln for ln in text.splitlines() if ln.rstrip().endswith(" 0  0.00")], text
    doc = json.loads(out.read_text())
    assert doc["frame"] == "image" and doc["series_uid"]
    centres = np.array([s["center_mm"] for s in doc["spheres"]])
    assert {"center_mm", "radius_mm", "n_slices", "score"} <= set(doc["spheres"][0])
    # every truth sphere found once, nothing else, centres in LPS mm
    d, idx = cKDTree(centres).query(scan.spheres_image_mm)
    assert len(centres) == len(scan.spheres_image_mm) and len(set(idx)) == len(idx)
    assert d.max() < MATCH_MM and d.mean() < 0.1


def test_detect_refuses_a_folder_without_ct(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    (tmp_path / "notes.txt").write_text("not DICOM")
    assert main(["detect", str(tmp_path)]) == EXIT_INPUT
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "no CT image series found" in err and "notes.txt" in err


def test_simulate_cone_beam_preset_then_detect(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    """``oarmreg simulate --preset cbct-ci`` (the cone-beam simulator, numpy FDK) writes a series
    that ``oarmreg detect`` reads: every fully imaged sphere of truth.json found, nothing else."""
    series, out = tmp_path / "cbct", tmp_path / "det.json"
    assert main(["simulate", "--out", str(series), "--preset", "cbct-ci", "--seed", "4"]) == 0
    truth = json.loads((series / "truth.json").read_text())
    assert truth["settings"]["preset_name"] == "cbct-ci" and truth["settings"]["n_views"] == 120
    capsys.readouterr()
    assert main(["detect", str(series), "--json", str(out)]) == 0
    table = capsys.readouterr().out
    # issue 34: spheres the estimator fitted no circles to were listed 'nan  0  0.00'; now '-'
    assert "nan" not in table and not re.search(r"\s0\s+0\.00\s*$", table, re.M), table
    centres = np.array([s["center_mm"] for s in json.loads(out.read_text())["spheres"]])
    expected = np.array(truth["spheres_image_mm"])
    assert len(expected) >= 20
    d, idx = cKDTree(centres).query(expected)
    assert len(centres) == len(expected) and len(set(idx)) == len(idx)
    assert d.max() < MATCH_MM


def test_detect_uses_the_phantom_materials_method_as_the_service_does(export, tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    """No ``--method``: the estimator the service would use for the phantom's sphere material
    (steel → ``rays``; a tungsten-carbide phantom file → ``core``); ``--method`` overrides it."""
    from registration.detection import method_for_material
    from registration.io.resources import default_phantom

    folder, _ = export
    assert main(["detect", str(folder), "--json", str(tmp_path / "a.json")]) == 0
    assert json.loads((tmp_path / "a.json").read_text())["method"] == method_for_material("steel") == "rays"
    wc = tmp_path / "wc.toml"
    text = default_phantom().read_text()
    assert "sphere_material" not in text  # the default file relies on the default (steel)
    wc.write_text(text.replace("units = ", 'sphere_material = "tungsten_carbide"\nunits = ', 1))
    assert main(["detect", str(folder), "--phantom", str(wc), "--json", str(tmp_path / "b.json")]) == 0
    assert json.loads((tmp_path / "b.json").read_text())["method"] == "core"
    assert main(["detect", str(folder), "--method", "subvoxel", "--json", str(tmp_path / "c.json")]) == 0
    assert json.loads((tmp_path / "c.json").read_text())["method"] == "subvoxel"
    capsys.readouterr()


def test_detect_refuses_a_bad_phantom_file_with_the_config_exit_code(export, tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    from service.error_map import EXIT_CONFIG

    folder, _ = export
    bad = tmp_path / "bad.toml"
    bad.write_text("this is = = not toml")
    assert main(["detect", str(folder), "--phantom", str(bad)]) == EXIT_CONFIG
    err = capsys.readouterr().err
    assert "bad.toml" in err


@pytest.fixture(scope="module")
def wc_export(tmp_path_factory: pytest.TempPathFactory, phantom):  # type: ignore[no-untyped-def]
    """A tungsten-carbide series and the phantom file that names the material."""
    from mocks.oarm.simulator import SceneExtras
    from registration.io.resources import default_phantom

    settings = AcquisitionSettings.preset("demo", rows=256, columns=256, n_views=180)
    scan = simulated_scan(phantom, demo_pose(), settings, SceneExtras(sphere_material="tungsten_carbide"))
    root = tmp_path_factory.mktemp("cli-detect-wc")
    write_dicom_series(scan, root / "series")
    toml = root / "wc.toml"
    toml.write_text(
        default_phantom().read_text().replace("units = ", 'sphere_material = "tungsten_carbide"\nunits = ', 1)
    )
    return root / "series", toml


@pytest.mark.parametrize("material", ["steel", "tungsten_carbide"])
def test_detect_and_register_find_the_same_spheres(  # type: ignore[no-untyped-def]
    material: str, export, wc_export, phantom, tmp_path: Path, capsys
) -> None:
    """``oarmreg detect`` and ``oarmreg register`` choose detection settings in one place (the
    phantom file's material, as the service): on the same series they report the same estimator
    and the same sphere centres, for steel (``rays``) and tungsten carbide (``core``)."""
    from registration.detection import method_for_material
    from registration.io.points import write_json
    from registration.io.resources import default_phantom

    folder, phantom_file = (export[0], default_phantom()) if material == "steel" else wc_export
    det_json, reg_json, robot_json = tmp_path / "det.json", tmp_path / "reg.json", tmp_path / "robot.json"
    # robot frame = phantom frame: any rigid pose of the phantom registers
    write_json(robot_json, {"spheres_mm": phantom.centres_phantom_mm.tolist()})
    assert main(["detect", str(folder), "--phantom", str(phantom_file), "--json", str(det_json)]) == 0
    args = ["register", str(folder), "--robot-points", str(robot_json), "--json", str(reg_json)]
    assert main([*args, "--phantom", str(phantom_file)]) == 0
    capsys.readouterr()
    det, reg = json.loads(det_json.read_text()), json.loads(reg_json.read_text())
    assert det["method"] == reg["provenance"]["detection_method"] == method_for_material(material)
    detected = np.array([s["center_mm"] for s in det["spheres"]])
    used = np.array([s["image_mm"] for s in reg["spheres"]])
    assert reg["n_detected"] == len(detected) == reg["n_matched"] == len(phantom.centres_phantom_mm)
    order = np.lexsort(detected.T)
    assert np.array_equal(detected[order], used[np.lexsort(used.T)])


def test_detect_overlay_marks_every_sphere_and_every_refusal_inside_the_figure(  # type: ignore[no-untyped-def]
    export, tmp_path: Path, capsys, monkeypatch
) -> None:
    """``--overlay PNG``: a red + on each detected centre (at its voxel column / row), one legend
    entry per rejection reason without its numbers, nothing drawn outside the figure."""
    from dataclasses import replace

    from registration.detection import detect_spheres
    from registration.detection.records import Rejection
    from registration.dicom import load_series
    from service.cli.commands.scan_inputs import detection_params_for_phantom
    from service.registrations.overlay import write_detection_overlay
    from tests.helpers.figures import assert_inside, capture_figures

    folder, _ = export
    png = tmp_path / "overlay.png"
    assert main(["detect", str(folder), "--overlay", str(png)]) == 0
    assert f"wrote {png}" in capsys.readouterr().out
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    volume = load_series(folder, unique=True)
    found = detect_spheres(volume, detection_params_for_phantom(None))
    c = found.centres_image_mm[0]
    extra = (
        Rejection(tuple(c + 20.0), "elongated or oversized metal (12.0 × 40.0 mm)"),
        Rejection(
            tuple(c + 30.0), "blob volume 41.2 mm³ > 20.1 mm³ (Ø2.5 mm sphere with blooming): wrong size"
        ),
        Rejection(
            tuple(c + 40.0), "blob volume 33.0 mm³ > 20.1 mm³ (Ø2.5 mm sphere with blooming): wrong size"
        ),
    )
    result = replace(found, rejections=(*found.rejections, *extra))
    drawn = capture_figures(monkeypatch)
    write_detection_overlay(volume, result, tmp_path / "o2.png")
    fig = drawn[0]
    ax = fig.axes[0]
    plus = next(line for line in ax.get_lines() if line.get_marker() == "+")
    ijk = volume.image_to_voxel(found.centres_image_mm)
    assert np.allclose(np.c_[plus.get_xdata(), plus.get_ydata()], ijk[:, :2])
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert f"detected ({len(found.spheres)}, {found.method})" in labels
    assert "rejected: elongated or oversized metal (1)" in labels
    assert "rejected: blob volume … mm³ > … mm³ (2)" in labels  # two volumes, one cause
    assert_inside(fig, ax.title, fig.legends[0])
