"""QA protocols over HTTP (issue #21): create, list, read; a verification naming one is checked
before it runs; bad ids and bodies answer 4xx problem details, never 500; records survive."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from tests.faults.conftest import TOKEN, Running, fault_settings, mock_robot, serve
from tests.helpers.tokens import make_token

POSES = [
    {"name": "p1", "joints_rad": [0.0, 0.0, 1.5708, 0.0, 0.7854, 0.0]},
    {"name": "p2", "joints_rad": [0.0, 0.0, 1.5708, 0.0, 0.7854, 0.3]},
]
READONLY = make_token()


@pytest.fixture(scope="module")
def svc(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Running]:
    root = tmp_path_factory.mktemp("qa")
    with mock_robot() as mock, serve(fault_settings(root, mock.url, api_readonly_token=READONLY)) as s:
        yield s


def _create(svc: Running, name: str, poses: Any = POSES, **kw: Any) -> Any:
    return svc.client.post("/qa/protocols", json={"name": name, "poses": poses, **kw})


def _problem(r: Any, status: int) -> dict[str, Any]:
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/problem+json"), r.headers
    body: dict[str, Any] = r.json()
    assert body["status"] == status and body["detail"], body
    return body


def test_a_protocol_is_stored_and_read_back_as_given(svc: Running) -> None:
    r = _create(svc, "weekly", description="Monday 07:00, before the first case")
    assert r.status_code == 201, r.text
    made = r.json()
    assert made["name"] == "weekly" and made["poses"] == POSES
    assert svc.client.get(f"/qa/protocols/{made['id']}").json() == made
    listed = svc.client.get("/qa/protocols", params={"limit": 1000}).json()
    assert made in listed
    audit = svc.client.get("/audit").json()
    assert any(a["action"] == "qa_protocol_create" and a["target_id"] == made["id"] for a in audit), audit


def test_a_name_is_never_reused(svc: Running) -> None:
    assert _create(svc, "monthly").status_code == 201
    body = _problem(_create(svc, "monthly", poses=POSES[:1]), 409)
    assert "monthly" in body["detail"] and "new name" in body["detail"]
    # the first one is unchanged
    same = [p for p in svc.client.get("/qa/protocols").json() if p["name"] == "monthly"]
    assert len(same) == 1 and same[0]["poses"] == POSES


@pytest.mark.parametrize(
    ("poses", "says"),
    [
        ([], "poses"),
        ([{"name": "p1", "joints_rad": [0.0] * 5}], "joints_rad"),
        ([{"name": "p1", "joints_rad": [0.0] * 5 + [7.0]}], "J6"),
        ([POSES[0], POSES[0]], "repeated: p1"),
        ([{"name": "has space", "joints_rad": [0.0] * 6}], "name"),
    ],
)
def test_a_bad_protocol_is_refused_with_what_was_wrong(svc: Running, poses: Any, says: str) -> None:
    before = svc.client.get("/qa/protocols", params={"limit": 1000}).json()
    body = _problem(_create(svc, f"bad-{len(before)}", poses=poses), 422)
    assert says in str(body), body
    assert svc.client.get("/qa/protocols", params={"limit": 1000}).json() == before


@pytest.mark.parametrize("pid", ["0", "-1", "x", str(2**63)])
def test_a_bad_protocol_id_is_422_and_a_missing_one_404(svc: Running, pid: str) -> None:
    _problem(svc.client.get(f"/qa/protocols/{pid}"), 422)
    _problem(svc.client.get("/qa/protocols/999999"), 404)


@pytest.mark.parametrize(
    ("body", "status", "says"),
    [
        ({"qa_protocol_id": 999999, "qa_pose": "p1"}, 404, "QA protocol 999999"),
        ({"qa_pose": "p1"}, 422, "both"),
        ({"qa_protocol_id": "1", "qa_pose": "p1"}, 422, "qa_protocol_id"),
        ({"qa_protocol_id": 0, "qa_pose": "p1"}, 422, "qa_protocol_id"),
    ],
)
def test_verify_naming_a_bad_protocol_is_refused_before_it_runs(
    svc: Running, body: dict[str, Any], status: int, says: str
) -> None:
    # no registration is current: a verification that ran would answer 409; these must not run
    n_ver = svc.client.get("/status").json()["counts"]["verifications"]
    r = _problem(svc.client.post("/verify", json=body), status)
    assert says in str(r), r
    assert svc.client.get("/status").json()["counts"]["verifications"] == n_ver


def test_verify_naming_a_pose_the_protocol_lacks_is_refused(svc: Running) -> None:
    pid = _create(svc, "pose-check").json()["id"]
    body = _problem(svc.client.post("/verify", json={"qa_protocol_id": pid, "qa_pose": "p9"}), 422)
    assert "no pose 'p9'" in body["detail"] and "p1, p2" in body["detail"]
    # a valid protocol and pose passes the check and reaches the verification itself (no registration)
    r = svc.client.post("/verify", json={"qa_protocol_id": pid, "qa_pose": "p2"})
    assert _problem(r, 409)["title"] == "No current registration"


def test_the_read_only_token_lists_but_cannot_create(svc: Running) -> None:
    ro = {"Authorization": f"Bearer {READONLY}"}
    assert svc.client.get("/qa/protocols", headers=ro).status_code == 200
    assert (
        svc.client.post("/qa/protocols", json={"name": "ro", "poses": POSES}, headers=ro).status_code == 403
    )
    assert svc.client.get("/qa/protocols", headers={"Authorization": "Bearer " + "x" * 20}).status_code == 401
    assert TOKEN not in str(svc.client.get("/qa/protocols").json())
