"""Points / targets / registration JSON files, and the `register` / `verify` CLI on point files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from registration.errors import InputFileUnreadableError, PointsFileError
from registration.io.points import (
    read_points,
    read_registration,
    read_targets,
    write_json,
    write_points,
    write_targets,
)
from registration.model import frames
from registration.model.phantom import Phantom
from service.cli.main import main
from service.error_map import EXIT_REFUSED
from tests.helpers.documents import REGISTRATION_DOC_KEYS

PTS = [[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 20.0, 0.0], [0.0, 0.0, 30.0]]


def _write(tmp_path: Path, text: str, name: str = "p.json") -> Path:
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return p


def test_points_round_trip(tmp_path: Path) -> None:
    p = write_points(tmp_path / "sub" / "pts.json", PTS, frame="robot")
    np.testing.assert_array_equal(read_points(p), PTS)
    assert json.loads(p.read_text())["frame"] == "robot"
    assert not list((tmp_path / "sub").glob(".*part"))  # atomic write leaves nothing behind


def test_targets_round_trip(tmp_path: Path) -> None:
    p = write_targets(tmp_path / "t.json", [[150.0, 0.0, 0.0]])
    np.testing.assert_array_equal(read_targets(p), [[150.0, 0.0, 0.0]])


def test_missing_file(tmp_path: Path) -> None:
    """A file-system problem, not bad content: exit 8 (docs/cli.md), issue 42 item 4."""
    with pytest.raises(InputFileUnreadableError, match="no such file"):
        read_points(tmp_path / "nope.json")


def test_directory_instead_of_file(tmp_path: Path) -> None:
    with pytest.raises(InputFileUnreadableError, match="directory"):
        read_points(tmp_path)


def test_invalid_json_names_line(tmp_path: Path) -> None:
    with pytest.raises(PointsFileError, match="line 2"):
        read_points(_write(tmp_path, '{"spheres_mm":\n [[1,2,3],]}'))


def test_not_an_object(tmp_path: Path) -> None:
    with pytest.raises(PointsFileError, match="JSON object"):
        read_points(_write(tmp_path, "[[1, 2, 3]]"))


def test_missing_key_lists_found_keys(tmp_path: Path) -> None:
    with pytest.raises(PointsFileError, match=r'missing key "spheres_mm".*centres'):
        read_points(_write(tmp_path, '{"centres": []}'))


def test_not_a_list(tmp_path: Path) -> None:
    with pytest.raises(PointsFileError, match="list"):
        read_points(_write(tmp_path, '{"spheres_mm": 3}'))


def test_bad_row(tmp_path: Path) -> None:
    with pytest.raises(PointsFileError, match=r"\[1\] must be \[x, y, z\]"):
        read_points(_write(tmp_path, '{"spheres_mm": [[1,2,3],[1,2],[4,5,6]]}'))


def test_string_values_refused(tmp_path: Path) -> None:
    with pytest.raises(PointsFileError, match="3 numbers"):
        read_points(_write(tmp_path, '{"spheres_mm": [[1,2,"3"],[1,2,4],[4,5,6]]}'))


def test_non_finite_refused(tmp_path: Path) -> None:
    with pytest.raises(PointsFileError, match="not finite"):
        read_points(_write(tmp_path, '{"spheres_mm": [[1,2,3],[1,2,NaN],[4,5,6]]}'))


def test_huge_values_refused(tmp_path: Path) -> None:
    with pytest.raises(PointsFileError, match="in mm"):
        read_points(_write(tmp_path, '{"spheres_mm": [[1,2,3],[1,2,1e9],[4,5,6]]}'))


def test_too_few_points(tmp_path: Path) -> None:
    with pytest.raises(PointsFileError, match="at least 3"):
        read_points(_write(tmp_path, '{"spheres_mm": [[1,2,3],[4,5,6]]}'))


def test_metres_detected(tmp_path: Path) -> None:
    m = (np.asarray(PTS) / 1000.0).tolist()
    with pytest.raises(PointsFileError, match="metres"):
        read_points(write_points(tmp_path / "m.json", m))


def test_registration_round_trip_and_refusal(tmp_path: Path) -> None:
    t = frames.make_transform(Rotation.random(random_state=1).as_matrix(), [1.0, 2.0, 3.0])
    p = write_json(tmp_path / "r.json", {"image_from_robot": t.tolist()})
    np.testing.assert_allclose(read_registration(p), t)
    r = write_json(tmp_path / "refused.json", {"refused": True, "reason": "ambiguous", "error": "X"})
    with pytest.raises(PointsFileError, match="refused registration"):
        read_registration(r)


def test_registration_not_rigid(tmp_path: Path) -> None:
    p = write_json(tmp_path / "r.json", {"image_from_robot": np.diag([1.0, 1.0, -1.0, 1.0]).tolist()})
    with pytest.raises(PointsFileError, match="reflection"):
        read_registration(p)


def test_registration_missing_matrix(tmp_path: Path) -> None:
    p = write_json(tmp_path / "r.json", {"fre_mm": 0.1})
    with pytest.raises(PointsFileError, match="image_from_robot"):
        read_registration(p)


# ---------------------------------------------------------------- CLI on point files


def _scene(
    phantom: Phantom, tmp_path: Path, seed: int, *, mirror: bool = False
) -> tuple[Path, Path, np.ndarray]:
    rng = np.random.default_rng(seed)
    robot = frames.apply(
        frames.make_transform(Rotation.random(random_state=seed).as_matrix(), [400, 0, 300]),
        phantom.centres_phantom_mm,
    )
    truth = frames.make_transform(Rotation.random(random_state=seed + 1).as_matrix(), [10, -20, 100])
    image = frames.apply(truth, robot) + rng.normal(0, 0.05, robot.shape)
    image = image[rng.permutation(len(image))[2:]]
    if mirror:
        image = image * [1.0, 1.0, -1.0]
    return write_points(tmp_path / "robot.json", robot), write_points(tmp_path / "image.json", image), truth


def test_cli_register_and_verify(
    phantom: Phantom, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    robot_p, image_p, truth = _scene(phantom, tmp_path, 3)
    targets = write_targets(tmp_path / "t.json", [[550.0, 0.0, 300.0]])
    out = tmp_path / "reg.json"
    rc = main(
        [
            "register",
            "--image-points",
            str(image_p),
            "--robot-points",
            str(robot_p),
            "--targets-robot",
            str(targets),
            "--json",
            str(out),
        ]
    )
    assert rc == 0
    text = capsys.readouterr().out
    assert "26 matched" in text and "FRE" in text and "one-scan TRE" in text and "symmetry margin" in text
    d = json.loads(out.read_text())
    for key in REGISTRATION_DOC_KEYS:
        assert key in d
    assert d["n_expected"] == 28 and d["n_detected"] == 26 and d["n_matched"] == 26
    assert d["provenance"]["robot_points_sha256"] and d["provenance"]["phantom"] == "bai2018_cube"
    robot = read_points(robot_p)
    np.testing.assert_allclose(
        frames.apply(np.asarray(d["image_from_robot"]), robot), frames.apply(truth, robot), atol=0.1
    )
    # verify the registration on the same scan (the paper would use a second pose)
    png = tmp_path / "hist.png"
    vout = tmp_path / "ver.json"
    rc = main(
        [
            "verify",
            "--image-points",
            str(image_p),
            "--robot-points",
            str(robot_p),
            "--registration",
            str(out),
            "--json",
            str(vout),
            "--histogram",
            str(png),
        ]
    )
    assert rc == 0
    v = json.loads(vout.read_text())
    assert v["n_matched"] == 26 and v["rms_mm"] < 0.2
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_refusal_writes_json_and_exits_nonzero(
    phantom: Phantom, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    robot_p, image_p, _ = _scene(phantom, tmp_path, 4, mirror=True)
    out = tmp_path / "reg.json"
    rc = main(
        ["register", "--image-points", str(image_p), "--robot-points", str(robot_p), "--json", str(out)]
    )
    assert rc == EXIT_REFUSED
    assert "mirror image" in capsys.readouterr().err
    d = json.loads(out.read_text())
    assert d["refused"] is True and d["error"] == "MirroredInputError" and "slice order" in d["reason"]


def test_cli_needs_exactly_one_image_source(phantom: Phantom, tmp_path: Path) -> None:
    robot_p, _, _ = _scene(phantom, tmp_path, 5)
    assert main(["register", "--robot-points", str(robot_p)]) != 0


def test_cli_prior_rotation_parsing(phantom: Phantom, tmp_path: Path) -> None:
    from service.cli.commands.register import parse_prereg, parse_prior

    np.testing.assert_allclose(parse_prior("0,0,90"), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    p = write_json(tmp_path / "prior.json", {"rotation": np.eye(3).tolist()})
    np.testing.assert_allclose(parse_prior(str(p)), np.eye(3))
    with pytest.raises(PointsFileError):
        parse_prior("1,2")
    assert parse_prereg("0:3,1:2,5:7,9:9") == [(0, 3), (1, 2), (5, 7), (9, 9)]
    with pytest.raises(PointsFileError):
        parse_prereg("0:3,1:2")
