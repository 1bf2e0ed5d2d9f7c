"""Issue #21 over HTTP (the browser tests are in tests/browser): which paths are public, the
Content-Security-Policy, CORS pre-flights without a token, the page's files in the wheel.

The real app under uvicorn on loopback (the fault suite's ``serve``); no browser here.
"""

from __future__ import annotations

import fnmatch
import re
import tomllib
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from tests.faults.conftest import TOKEN, Running, fault_settings, mock_robot, serve
from tests.helpers import http
from tests.helpers.tokens import make_token

REPO = Path(__file__).resolve().parents[2]
NAV_UI = "http://nav-ui.example:8080"
READONLY = make_token()
PUBLIC = ("/", "/favicon.ico", "/docs", "/static/app.js", "/static/app.css", "/static/docs.js",
          "/static/swagger/swagger-ui-bundle.js", "/static/swagger/swagger-ui.css", "/health")  # fmt: skip
"""Every path that answers without a token (the page, its assets, the docs shell, liveness)."""


@pytest.fixture(scope="module")
def svc(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Running]:
    root = tmp_path_factory.mktemp("web")
    kw = {"api.allowed_origins": [NAV_UI], "api_readonly_token": READONLY}
    with mock_robot() as mock, serve(fault_settings(root, mock.url, **kw)) as s:
        yield s


def _data_routes(svc: Running) -> list[tuple[str, str]]:
    """(method, path with every id set to 1) of every route in the OpenAPI schema but /health."""
    return [
        (m.upper(), re.sub(r"\{[^}]+\}", "1", path))
        for path, item in svc.app.openapi()["paths"].items()
        if path != "/health"
        for m in item
    ]


@pytest.mark.parametrize("path", PUBLIC)
def test_public_paths_answer_without_a_token_with_the_csp(svc: Running, path: str) -> None:
    r = http.get(svc.base_url + path)
    assert r.status_code == 200, (path, r.text[:200])
    csp = r.headers["content-security-policy"]
    assert csp.startswith("default-src 'self'"), csp
    assert "unsafe-inline" not in csp and "unsafe-eval" not in csp
    assert r.headers["x-content-type-options"] == "nosniff"


def test_the_page_loads_nothing_from_elsewhere(svc: Running) -> None:
    html = http.get(svc.base_url + "/").text
    assert "<script>" not in html and " style=" not in html  # CSP: no inline script or style
    for needle in ("http://", "https://", "//cdn"):
        assert needle not in html.replace("http://www.w3.org", ""), needle
    assert http.get(svc.base_url + "/").headers["content-type"].startswith("text/html")
    assert http.get(svc.base_url + "/static/app.js").headers["content-type"].startswith("text/javascript")


def test_every_data_route_and_the_schema_need_the_token(svc: Running) -> None:
    routes = _data_routes(svc)
    assert ("GET", "/verifications") in routes and ("GET", "/status") in routes
    for method, path in [*routes, ("GET", "/openapi.json")]:
        r = http.request(method, svc.base_url + path, headers={"Content-Type": "application/json"})
        assert r.status_code == 401, (method, path, r.status_code)


def test_a_public_path_is_public_for_reading_only(svc: Running) -> None:
    r = http.post(svc.base_url + "/", headers={"Content-Type": "application/json"})
    assert r.status_code == 401
    assert http.get(svc.base_url + "/static/nope.js").status_code == 404
    assert http.get(svc.base_url + "/static/../status").status_code in (401, 404)
    assert http.get(svc.base_url + "/static/index.html").status_code == 404  # only at /


def test_static_files_revalidate_with_their_etag(svc: Running) -> None:
    r = http.get(svc.base_url + "/static/app.js")
    again = http.get(svc.base_url + "/static/app.js", headers={"If-None-Match": r.headers["etag"]})
    assert again.status_code == 304 and again.content == b""


def test_cors_preflight_from_a_listed_origin_needs_no_token(svc: Running) -> None:
    r = httpx.options(
        svc.base_url + "/registration/current",
        headers={
            "Origin": NAV_UI,
            "Access-Control-Request-Method": "GET",
            "Access-Control-Request-Headers": "authorization",
        },
    )
    assert r.status_code == 200, r.text
    assert r.headers["access-control-allow-origin"] == NAV_UI
    assert "authorization" in r.headers["access-control-allow-headers"].lower()
    assert "access-control-allow-credentials" not in r.headers  # the token is a header, not a cookie


def test_cors_real_request_still_needs_the_token(svc: Running) -> None:
    anon = http.get(svc.base_url + "/status", headers={"Origin": NAV_UI})
    assert anon.status_code == 401
    assert anon.headers["access-control-allow-origin"] == NAV_UI  # the UI can read why
    ok = http.get(svc.base_url + "/status", headers={"Origin": NAV_UI, "Authorization": f"Bearer {TOKEN}"})
    assert ok.status_code == 200 and ok.headers["access-control-allow-origin"] == NAV_UI


def test_cors_preflight_from_an_unlisted_origin_gets_no_allow_headers(svc: Running) -> None:
    r = httpx.options(
        svc.base_url + "/status",
        headers={"Origin": "http://evil.example", "Access-Control-Request-Method": "GET"},
    )
    assert r.status_code == 400
    assert "access-control-allow-origin" not in r.headers
    assert http.get(svc.base_url + "/status", headers={"Origin": "http://evil.example"}).status_code == 403


def test_without_listed_origins_there_is_no_cors(tmp_path: Path) -> None:
    with mock_robot() as mock, serve(fault_settings(tmp_path, mock.url)) as s:
        r = httpx.options(
            s.base_url + "/status", headers={"Origin": NAV_UI, "Access-Control-Request-Method": "GET"}
        )
        assert "access-control-allow-origin" not in r.headers and r.status_code in (401, 403)


def test_verifications_list_is_paginated(svc: Running) -> None:
    assert svc.client.get("/verifications").json() == []
    assert svc.client.get("/verifications", params={"limit": 0}).status_code == 422
    assert svc.client.get("/verifications", params={"offset": -1}).status_code == 422


def test_every_page_file_is_package_data() -> None:
    """The wheel carries the page: each file under service/http/web/static is in a listed (data) package
    and matches that package's package-data glob."""
    tool = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    static = REPO / "service" / "http" / "web" / "static"
    files = [p.relative_to(REPO) for p in static.rglob("*") if p.is_file()]
    assert len(files) >= 8
    missing = []
    for f in files:
        pkg = ".".join(f.parent.parts)
        globs = tool["package-data"].get(pkg, [])
        if pkg not in tool["packages"] or not any(fnmatch.fnmatchcase(f.name, g) for g in globs):
            missing.append(f.as_posix())
    assert not missing, f"not shipped (packages / package-data): {missing}"
