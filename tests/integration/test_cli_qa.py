"""``oarmreg qa protocol create|list`` (issue #21): stored in the service's database as the API
stores it; a bad pose or a taken name exits 4 with the reason and stores nothing."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from service.cli.main import main
from service.settings import load_settings
from service.store import Database


def _list(data: Path, capsys: pytest.CaptureFixture[str]) -> list[dict[str, object]]:
    capsys.readouterr()
    assert main(["qa", "protocol", "list", "--data", str(data)]) == 0
    rows: list[dict[str, object]] = json.loads(capsys.readouterr().out)
    return rows


def test_create_then_list_gives_the_poses_in_radians(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = tmp_path / "data"
    argv = ["qa", "protocol", "create", "weekly", "--data", str(data), "--degrees",
            "--pose", "p1=0,0,90,0,45,0", "--pose", "p2=0,0,90,0,45,17.19"]  # fmt: skip
    assert main(argv) == 0
    assert "stored with 2 poses" in capsys.readouterr().out
    (proto,) = _list(data, capsys)
    assert proto["name"] == "weekly"
    poses = proto["poses"]
    assert isinstance(poses, list) and [p["name"] for p in poses] == ["p1", "p2"]
    assert poses[1]["joints_rad"] == pytest.approx([0, 0, math.pi / 2, 0, math.pi / 4, math.radians(17.19)])
    db = Database.open(load_settings(None, {"data_dir": data}).db_path)
    try:
        assert any(a.action == "qa_protocol_create" and a.principal == "cli" for a in db.audit.list())
    finally:
        db.close()


@pytest.mark.parametrize(
    ("pose", "says"),
    [
        ("p1=0,0,0,0,0", "joints_rad"),
        ("p1", "NAME=J1"),
        ("p1=0,0,x,0,0,0", "NAME=J1"),
        ("p1=0,0,0,0,0,9", "J6"),
    ],
)
def test_a_bad_pose_exits_4_and_stores_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], pose: str, says: str
) -> None:
    data = tmp_path / "data"
    assert main(["qa", "protocol", "create", "bad", "--data", str(data), "--pose", pose]) == 4
    assert says in capsys.readouterr().err
    assert _list(data, capsys) == []


def test_a_taken_name_exits_4_and_keeps_the_first(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = tmp_path / "data"
    assert main(["qa", "protocol", "create", "m", "--data", str(data), "--pose", "a=0,0,0,0,0,0"]) == 0
    assert main(["qa", "protocol", "create", "m", "--data", str(data), "--pose", "b=1,0,0,0,0,0"]) == 4
    assert "exists already" in capsys.readouterr().err
    (proto,) = _list(data, capsys)
    assert [p["name"] for p in proto["poses"]] == ["a"]  # type: ignore[attr-defined]
