"""``GET /qa/trend`` / ``GET /qa/trend.csv`` and the QA drift rule in ``/status`` (issue #21).

The QA series is written through the service's own store into the data folder before start
(tests/integration/qa_seed.py); the figures read back must be the ones written."""

from __future__ import annotations

import csv
import io
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

from tests.faults.conftest import Running, fault_settings, mock_robot, serve
from tests.integration.qa_seed import seed_calibration, seed_qa_series

STEADY = [0.20, 0.22, 0.19, 0.21]
UNDER_CAL = [0.4, 0.9]


@contextmanager
def _start(root: Path) -> Iterator[Running]:
    with mock_robot() as mock, serve(fault_settings(root, mock.url)) as s:
        yield s


def _data(root: Path) -> Path:
    (root / "data").mkdir(parents=True, exist_ok=True)
    return root / "data"


@pytest.fixture(scope="module")
def steady(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Running, int, list[int], list[int]]]:
    root = tmp_path_factory.mktemp("qa-steady")
    _, vids = seed_qa_series(_data(root), STEADY, fre_mm=0.18)
    cal = seed_calibration(_data(root))
    _, cal_vids = seed_qa_series(
        _data(root), UNDER_CAL, calibration_id=cal, fre_mm=0.31, face_offset_mm=-0.012
    )
    with _start(root) as s:
        yield s, cal, vids, cal_vids


def _problem(r: Any, status: int) -> dict[str, Any]:
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/problem+json"), r.headers
    body: dict[str, Any] = r.json()
    assert body["status"] == status and body["detail"], body
    return body


def _drift(svc: Running) -> list[dict[str, Any]]:
    st = svc.client.get("/status").json()
    return [p for p in st["problem_details"] if p["type"] == "qa-drift"]


def test_the_trend_gives_every_qa_check_and_fre_as_written(
    steady: tuple[Running, int, list[int], list[int]],
) -> None:
    svc, cal, vids, cal_vids = steady
    t = svc.client.get("/qa/trend").json()
    assert [c["verification_id"] for c in t["checks"]] == vids + cal_vids
    assert [c["mean_mm"] for c in t["checks"]] == STEADY + UNDER_CAL
    assert [c["max_mm"] for c in t["checks"]] == [2 * m for m in STEADY + UNDER_CAL]
    assert [c["passed"] for c in t["checks"]] == [True] * 4 + [True, False]  # max 0.8, 1.8 vs gate 1.0 mm
    assert [c["calibration_id"] for c in t["checks"]] == [None] * 4 + [cal, cal]
    assert [c["pose"] for c in t["checks"]] == ["p1", "p2", "p1", "p2", "p1", "p2"]
    assert {c["protocol_name"] for c in t["checks"]} == {"weekly"}
    assert [(f["fre_mm"], f["calibration_id"]) for f in t["fre"]] == [(0.18, None), (0.31, cal)]
    # the face offset β (issue #43) as stored; null where none was fitted
    assert [f["face_offset_mm"] for f in t["fre"]] == [None, -0.012]
    # the rule reads the active calibration's checks (none active: the nominal model's): steady
    assert t["drift"]["drifting"] is False and t["drift"]["means_mm"] == STEADY[-3:]
    assert t["drift"]["window"] == 3 and t["drift"]["limit_mm"] == 0.5
    assert _drift(svc) == []


def test_the_trend_pages_and_filters_by_calibration(
    steady: tuple[Running, int, list[int], list[int]],
) -> None:
    svc, cal, vids, cal_vids = steady
    page = svc.client.get("/qa/trend", params={"limit": 2, "offset": 1}).json()
    assert [c["verification_id"] for c in page["checks"]] == vids[1:3]
    only = svc.client.get("/qa/trend", params={"calibration_id": cal}).json()
    assert [c["verification_id"] for c in only["checks"]] == cal_vids
    assert [f["fre_mm"] for f in only["fre"]] == [0.31]


@pytest.mark.parametrize(
    ("params", "status"),
    [
        ({"calibration_id": 0}, 422),
        ({"calibration_id": "x"}, 422),
        ({"calibration_id": 2**63}, 422),
        ({"limit": 0}, 422),
        ({"offset": -1}, 422),
        ({"calibration_id": 999999}, 404),
    ],
)
@pytest.mark.parametrize("path", ["/qa/trend", "/qa/trend.csv"])
def test_bad_trend_queries_answer_problem_details(
    steady: tuple[Running, int, list[int], list[int]], path: str, params: dict[str, Any], status: int
) -> None:
    svc = steady[0]
    body = _problem(svc.client.get(path, params=params), status)
    if status == 404:
        assert "calibration 999999" in body["detail"] and "GET /calibrations" in body["detail"]
    assert len(svc.client.get("/qa/trend").json()["checks"]) == 6  # records intact


def test_the_trend_is_behind_the_token(steady: tuple[Running, int, list[int], list[int]]) -> None:
    svc = steady[0]
    for path in ("/qa/trend", "/qa/trend.csv"):
        assert svc.client.get(path, headers={"Authorization": ""}).status_code == 401
        assert svc.client.get(path, headers={"Authorization": "Bearer " + "x" * 20}).status_code == 401


def test_the_csv_says_what_the_json_says(steady: tuple[Running, int, list[int], list[int]]) -> None:
    svc = steady[0]
    for params in ({}, {"calibration_id": steady[1]}, {"limit": 3, "offset": 2}):
        r = svc.client.get("/qa/trend.csv", params=params)
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/csv"), r.headers
        rows = list(csv.DictReader(io.StringIO(r.text)))
        t = svc.client.get("/qa/trend", params=params).json()
        checks = [x for x in rows if x["kind"] == "qa_check"]
        fre = [x for x in rows if x["kind"] == "fre"]
        assert len(rows) == len(checks) + len(fre)
        assert [
            (int(x["id"]), x["created_at"], float(x["mean_mm"]), float(x["max_mm"]), x["passed"] == "PASS",
             x["pose"], x["protocol_name"], int(x["calibration_id"]) if x["calibration_id"] else None)
            for x in checks
        ] == [
            (c["verification_id"], c["created_at"], c["mean_mm"], c["max_mm"], c["passed"], c["pose"],
             c["protocol_name"], c["calibration_id"])
            for c in t["checks"]
        ]  # fmt: skip
        assert [(int(x["id"]), float(x["fre_mm"])) for x in fre] == [
            (f["registration_id"], f["fre_mm"]) for f in t["fre"]
        ]
        assert [float(x["face_offset_mm"]) if x["face_offset_mm"] else None for x in fre] == [
            f["face_offset_mm"] for f in t["fre"]
        ]


@pytest.mark.parametrize(
    ("means", "says"),
    [
        ([0.2, 0.6, 0.7, 0.65], "mean 0.65 mm exceeds qa.drift_mean_mm 0.5 mm"),
        ([0.1, 0.1, 0.2, 0.35], "rose at every check, by 0.25 mm"),
    ],
)
def test_a_drifting_series_lists_recalibrate_in_status(tmp_path: Path, means: list[float], says: str) -> None:
    seed_qa_series(_data(tmp_path), means)
    with _start(tmp_path) as svc:
        (p,) = _drift(svc)
        assert p["title"] == "Recalibrate: QA drifting"
        assert says in p["detail"] and "nominal robot model" in p["detail"], p
        assert "calibration session" in p["detail"]
        assert svc.client.get("/qa/trend").json()["drift"]["drifting"] is True
        assert svc.client.get("/ready").status_code == 503


@pytest.mark.parametrize(
    "means",
    [
        [0.1, 0.2, 0.15, 0.45],  # the last 3 rise by 0.25 mm from first to last, but not at every check
        [0.5, 0.3, 0.35, 0.45],  # the last 3 rise at every check, by 0.15 mm only
        [0.9, 0.9],  # fewer than drift_window checks (the verification gate judges each)
    ],
)
def test_a_series_that_does_not_drift_lists_nothing(tmp_path: Path, means: list[float]) -> None:
    seed_qa_series(_data(tmp_path), means)
    with _start(tmp_path) as svc:
        assert _drift(svc) == []
        assert svc.client.get("/qa/trend").json()["drift"]["drifting"] is False
