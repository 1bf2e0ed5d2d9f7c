"""Issue #21 in a real browser: the OR's status page in headless Chromium (Debian's, via Playwright).

One service (mock controller, simulated scans, uvicorn on loopback) and one browser per module;
each test opens its own browser context (fresh sessionStorage, no shared page state) and checks
that no request left the origin and the console stayed free of errors.  Waits are on selectors
and page conditions with deadlines, never on time.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.browser import harness as h

# Skipped on a developer machine without Chromium; in CI (.ci/run installs it) a missing browser fails.
pytestmark = pytest.mark.skipif(
    h.chromium_missing() is not None and os.environ.get("CI") != "true", reason=str(h.chromium_missing())
)

LIVE_DEADLINE_MS = 2000
"""A new registration must appear this soon after /register answers, without a reload (issue #21)."""
QUOTA_MB = 10000.0
"""A retention quota far above what the module's scans use (nothing is deleted), shown on the page."""
LOAD_DEADLINE_MS = 5000
"""The page shows the current registration this soon after opening (issue #21, done-when)."""


@pytest.fixture(scope="module")
def world(phantom: Any) -> h.World:
    return h.make_world(phantom)


@pytest.fixture(scope="module")
def nav_ui() -> Iterator[Any]:
    """A navigation UI on a second origin (another loopback port) that calls the API with the token."""
    from starlette.applications import Starlette
    from starlette.responses import HTMLResponse, Response
    from starlette.routing import Route

    from service.cli.commands.serve import serve_in_thread

    page = HTMLResponse('<!doctype html><title>nav ui</title><script src="/nav.js"></script>')
    script = (Path(__file__).with_name("nav_ui.js")).read_text()
    app = Starlette(
        routes=[
            Route("/", lambda _r: page),
            Route("/nav.js", lambda _r: Response(script, media_type="text/javascript")),
        ]
    )
    with serve_in_thread(app) as server:
        yield server


@pytest.fixture(scope="module")
def svc(
    tmp_path_factory: pytest.TempPathFactory, world: h.World, nav_ui: Any
) -> Iterator[tuple[h.Service, dict[str, Any]]]:
    root = tmp_path_factory.mktemp("page")
    kw = {"api.allowed_origins": [nav_ui.base_url], "igtl.enabled": True, "igtl.port": 0,
          "retention.max_disk_mb": QUOTA_MB}  # fmt: skip
    with h.running_service(root, world, **kw) as s:
        yield s, h.build_history(s, world)


def _current(svc: h.Service) -> dict[str, Any]:
    """Make sure a registration of a complete scan at Q1 is current; return /registration/current."""
    r = svc.client.get("/registration/current")
    if r.status_code == 200:
        return r.json()  # type: ignore[no-any-return]
    svc.hold_at(h.Q1)
    scans = svc.client.get("/scans").json()
    scan_id = next(s["id"] for s in scans if s["status"] == "complete" and s["joints"]["still"])
    reg = svc.register(scan_id)
    assert reg.status_code == 200, reg.text
    return svc.client.get("/registration/current").json()  # type: ignore[no-any-return]


def _signed_in(context: Any, svc: h.Service) -> h.PageWatch:
    w = h.watched_page(context, svc.base_url)
    w.page.goto(f"{svc.base_url}/#token={h.TOKEN}")
    w.page.wait_for_selector("#live.ok")  # signed in, event stream open
    return w


def _box(locator: Any) -> dict[str, float]:
    """``locator``'s box once it has one: a refresh that re-renders the table or the alarm (an event
    arriving) detaches the element for a moment, and Playwright then answers None, not a box."""
    locator.wait_for(state="visible")
    for _ in range(50):
        box = locator.bounding_box()
        if box is not None:
            return box  # type: ignore[no-any-return]
        locator.wait_for(state="visible")
    raise AssertionError(f"{locator} never had a box")


def _showing(context: Any, svc: h.Service, registration_id: int) -> h.PageWatch:
    """A signed-in page once it shows registration ``registration_id`` as the current one."""
    w = _signed_in(context, svc)
    w.page.wait_for_function(
        "id => document.getElementById('current-id').dataset.value === String(id)", arg=registration_id
    )
    return w


WITHDRAWN = (("/registration/current", 409),)
"""The failed load a test that withdraws the current registration provokes: the page reads /status
(a registration is current), the test withdraws it, the page's /registration/current then answers
409 and Chromium logs it; under load that window is wide.  The page handles it (nothing current)."""


def assert_clean(w: h.PageWatch, provoked: tuple[tuple[str, int], ...] = ()) -> None:
    """No request left the origin; no console error but the failed loads in ``provoked``."""
    assert w.requests, "the page made no request at all"
    assert not w.foreign_requests(), f"requests left the origin: {w.foreign_requests()}"
    errors = w.console_errors(provoked)
    assert not errors, f"console errors: {errors}"


# ---- tests ---------------------------------------------------------------------------------------


def test_fragment_sign_in_shows_the_current_registration_as_the_api_gives_it(
    context: Any, svc: tuple[h.Service, dict[str, Any]]
) -> None:
    s, _ = svc
    cur = _current(s)
    w = h.watched_page(context, s.base_url)
    sent: list[dict[str, str]] = []
    w.page.on("request", lambda req: sent.append({"url": req.url, **req.headers}))
    w.page.goto(f"{s.base_url}/#token={h.TOKEN}")
    w.page.wait_for_function(
        "id => document.getElementById('current-id').dataset.value === String(id)",
        arg=cur["id"],
        timeout=LOAD_DEADLINE_MS,
    )
    p = w.page
    assert p.text_content("#current-fre") == f"{cur['fre_mm']:.4f}"
    assert float(p.get_attribute("#current-fre", "data-value")) == cur["fre_mm"]
    assert float(p.get_attribute("#current-fle", "data-value")) == cur["fle_mm"]
    assert float(p.get_attribute("#current-tre", "data-value")) == max(cur["predicted_tre_mm"])
    assert json.loads(p.get_attribute("#current-matrix", "data-value")) == cur["image_from_robot"]
    assert p.locator("#current-chart svg rect").count() == len(cur["spheres"])
    # issue 40 item 1: what backs the robot side, first, as REST says; never a green badge unverified
    ev = cur["evidence"]
    assert p.get_attribute("#current-evidence", "data-level") == ev["level"]
    assert p.text_content("#current-evidence-level") == ev["level"].upper()
    assert ev["summary"] in p.text_content("#current-evidence-text")
    if ev["level"] == "unverified":
        assert "ok" not in p.get_attribute("#current-badge", "class").split()
        assert "unverified" in p.text_content("#current-badge")
        assert ev["action"] in p.text_content("#current-evidence")
    # disk use against the retention quota: /status counts the scan files on disk, the page shows it
    disk = s.client.get("/status").json()["disk"]
    on_disk = sum(f.stat().st_size for f in s.watch.rglob("*") if f.is_file())
    assert on_disk > 0 and disk["scans_mb"] * 1024**2 == pytest.approx(on_disk, rel=1e-12)
    assert disk["quota_mb"] == QUOTA_MB and disk["data_dir_free_mb"] > 0
    assert float(p.get_attribute("#disk", "data-value")) == pytest.approx(disk["scans_mb"], rel=1e-12)
    assert f"of the {QUOTA_MB:.0f} MB quota" in p.text_content("#disk")
    # the token: out of the address bar, in sessionStorage, sent as the bearer header, never a cookie
    assert "token" not in p.url
    assert p.evaluate("sessionStorage.getItem('oarmreg.token')") == h.TOKEN
    assert context.cookies() == []
    api_calls = [r for r in sent if "/status" in r["url"]]
    assert api_calls and all(r.get("authorization") == f"Bearer {h.TOKEN}" for r in api_calls)
    assert not any(h.TOKEN in r["url"] for r in sent)
    assert_clean(w)


def test_form_sign_in_refuses_a_wrong_token_then_accepts_the_right_one(
    context: Any, svc: tuple[h.Service, dict[str, Any]]
) -> None:
    s, _ = svc
    w = h.watched_page(context, s.base_url)
    p = w.page
    p.goto(s.base_url + "/")
    p.wait_for_selector("#sign-in-form")
    assert p.is_hidden("#app")
    p.fill("#token", "not-the-token-0123456789")
    p.click("#sign-in-form button")
    p.wait_for_selector("#sign-in-error:has-text('refused')")
    assert p.is_hidden("#app") and p.evaluate("sessionStorage.getItem('oarmreg.token')") is None
    w.console.clear()  # the refused /status is logged by Chromium as a failed resource load
    p.fill("#token", h.TOKEN)
    p.click("#sign-in-form button")
    p.wait_for_selector("#live.ok")
    assert p.is_visible("#status") and p.text_content("#health") == "healthy"
    assert p.text_content("#link-state").startswith("connected")
    assert_clean(w)


def test_a_new_registration_appears_live_without_a_reload(
    context: Any, svc: tuple[h.Service, dict[str, Any]]
) -> None:
    s, _ = svc
    before = _current(s)
    w = _showing(context, s, before["id"])
    p = w.page
    p.evaluate("window.__sameDocument = true")
    reg = s.register(before["scan_id"])
    assert reg.status_code == 200, reg.text
    new = reg.json()
    p.wait_for_function(
        "id => document.getElementById('current-id').dataset.value === String(id)",
        arg=new["id"],
        timeout=LIVE_DEADLINE_MS,
    )
    assert p.evaluate("window.__sameDocument") is True  # no reload
    assert p.text_content("#current-fre") == f"{new['fre_mm']:.4f}"
    assert p.locator(f"#registrations-body tr[data-registration='{new['id']}']").count() == 1
    assert_clean(w)


def test_a_refusal_is_shown_in_plain_words_and_the_current_one_named(
    context: Any, svc: tuple[h.Service, dict[str, Any]]
) -> None:
    s, history = svc
    cur = _current(s)
    w = _signed_in(context, s)
    p = w.page
    moving_scan = history["refused"]["registration_id"]
    refused_scan = s.client.get(f"/registrations/{moving_scan}").json()["scan_id"]
    r = s.register(refused_scan)  # the scan taken while the robot moved: refused again, at once
    assert r.status_code == 409, r.text
    rid = r.json()["registration_id"]
    row = p.locator(f"#registrations-body tr[data-registration='{rid}'][data-status='refused']")
    row.wait_for()
    assert "Robot moved during the scan" in row.text_content()
    assert "Keep the robot still" in row.text_content()
    b = p.locator(f"#banners .banner:has-text('Registration {rid}')")
    b.wait_for()
    text = b.text_content()
    assert "was refused" in text and f"Registration {cur['id']} stays current" in text
    assert "What to do: Keep the robot still" in text
    assert p.get_attribute("#current-id", "data-value") == str(cur["id"])
    assert_clean(w)


def test_a_withdrawal_is_shown_and_nothing_is_current(
    context: Any, svc: tuple[h.Service, dict[str, Any]], world: h.World
) -> None:
    s, _ = svc
    _current(s)
    s.hold_at(h.Q1)
    uid, held = s.export(world.scan1, "partial", drop_last=2)
    partial = s.scan(uid)
    reg = s.register(partial["id"])
    assert reg.status_code == 200, reg.text
    w = _signed_in(context, s)
    p = w.page
    p.wait_for_function(
        "id => document.getElementById('current-id').dataset.value === String(id)", arg=reg.json()["id"]
    )
    h.copy_late_slices(held, Path(partial["folder"]))  # the rest of the series arrives late
    b = p.locator("#banners .banner:has-text('No current registration')")
    b.wait_for()
    text = b.text_content()
    assert f"Registration {reg.json()['id']} was withdrawn" in text and "instance(s) added" in text
    assert p.is_visible("#current-none") and p.text_content("#current-badge") == "none"
    p.locator(
        f"#registrations-body tr[data-registration='{reg.json()['id']}'][data-status='withdrawn']"
    ).wait_for()
    assert s.client.get("/registration/current").status_code == 409
    _current(s)  # leave a current registration for the other tests
    assert_clean(w, provoked=WITHDRAWN)


def test_verifications_show_the_gate_line_and_the_verdict(
    context: Any, svc: tuple[h.Service, dict[str, Any]], world: h.World
) -> None:
    s, history = svc
    passed = history["verification"]
    assert passed["passed"] and passed["gate_mm"] == 1.0
    _current(s)
    # a failed one: the scan shows the phantom at Q1 while the link reports J6 turned by 0.04 rad
    q = (*h.Q1[:5], h.Q1[5] + 0.04)
    s.hold_at(q)
    uid, _ = s.export(world.scan1, "wrong-pose")
    v = s.client.post("/verify", json={"scan_id": s.scan(uid)["id"]})
    s.hold_at(h.Q1)
    assert v.status_code == 200, v.text
    failed = v.json()
    assert not failed["passed"] and failed["max_mm"] > failed["gate_mm"]
    # a failed verification withdraws the registration it verified (issue #31): nothing is current
    gone = s.client.get("/registration/current")
    assert gone.status_code == 409 and gone.json()["verification_id"] == failed["id"], gone.text
    listed = s.client.get("/verifications", params={"limit": 100}).json()
    assert [x["id"] for x in listed] == sorted((x["id"] for x in listed), reverse=True)

    w = _signed_in(context, s)
    p = w.page
    row = p.locator(f"#verifications-body tr[data-verification='{failed['id']}']")
    row.wait_for()
    assert row.text_content().endswith("FAIL")
    row.click()
    p.wait_for_selector(f"#ver-title[data-verdict='FAIL']:has-text('Verification {failed['id']}')")
    assert float(p.locator("#ver-chart line.gate").get_attribute("data-gate")) == failed["gate_mm"]
    assert "FAIL" in p.text_content("#ver-chart")
    ticks = p.locator("#ver-chart text.ytick").all_text_contents()
    assert len(ticks) >= 2 and all(t.isdigit() for t in ticks), ticks  # sphere counts
    assert p.locator("#ver-errors span.bad").count() == sum(
        e["error_mm"] > failed["gate_mm"] for e in failed["errors"]
    )
    if passed["id"] in [x["id"] for x in listed[:10]]:
        p.click(f"#verifications-body tr[data-verification='{passed['id']}']")
        p.wait_for_selector(f"#ver-title[data-verdict='PASS']:has-text('Verification {passed['id']}')")
        assert "PASS" in p.text_content("#ver-chart")
    _current(s)  # leave a current registration for the other tests
    assert_clean(w)


def test_the_evidence_level_rises_on_the_page_after_a_verification_at_another_pose(
    context: Any, svc: tuple[h.Service, dict[str, Any]], world: h.World
) -> None:
    """Issue 40 item 1, in Chromium: a fresh registration of the Q1 scan reads UNVERIFIED first, with
    the action and no green badge; a passing verification at Q2 turns it VERIFIED, live."""
    s, _ = svc
    s.hold_at(h.Q1)
    uid, _ = s.export(world.scan1, "evidence-q1")
    fresh = s.register(s.scan(uid)["id"])
    assert fresh.status_code == 200, fresh.text
    reg = fresh.json()
    assert reg["evidence"]["level"] == "unverified"
    w = _showing(context, s, reg["id"])
    p = w.page
    p.wait_for_selector("#current-evidence[data-level='unverified']")
    assert p.text_content("#current-evidence-level") == "UNVERIFIED"
    assert "verify at another pose" in p.text_content("#current-evidence")
    assert "ok" not in p.get_attribute("#current-badge", "class").split()
    s.hold_at(h.Q2)
    uid, _ = s.export(world.scan2, "evidence")
    v = s.client.post("/verify", json={"scan_id": s.scan(uid)["id"]})
    s.hold_at(h.Q1)
    assert v.status_code == 200 and v.json()["passed"], v.text
    p.wait_for_selector("#current-evidence[data-level='verified']")
    assert p.text_content("#current-evidence-level") == "VERIFIED"
    assert f"verification {v.json()['id']}" in p.text_content("#current-evidence-text")
    assert_clean(w)


def test_a_failed_verification_withdraws_with_a_banner_and_the_chain_figure_comes_first(
    context: Any, svc: tuple[h.Service, dict[str, Any]], world: h.World
) -> None:
    """Issue #31 items 1 and 6: the card leads with the expected error at the working poses and says
    the cell is not calibrated; a failed verification withdraws the registration and the banner names
    the verification, the likely cause (at the registration's own joints the robot side cannot
    explain it: the phantom or the O-arm moved) and the action."""
    s, _ = svc
    cur = _current(s)
    w = _signed_in(context, s)
    p = w.page
    p.wait_for_function(
        "id => document.getElementById('current-id').dataset.value === String(id)", arg=cur["id"]
    )
    assert p.evaluate("document.getElementById('current-body').firstElementChild.id") == "current-expected"
    chain = cur["expected_error"]["predicted_chain_error_mm"]
    assert float(p.get_attribute("#current-chain", "data-value")) == chain == cur["predicted_chain_error_mm"]
    assert p.is_visible("#current-uncalibrated")
    warning = p.text_content("#current-uncalibrated")
    assert "This cell is not calibrated" in warning and f"about {chain:.1f} mm" in warning
    assert "One-scan TRE, this pose only" in p.text_content("#current-body dl.figures")
    # the phantom knocked 2 mm: the registration's pose again, its image shifted by 2 mm
    from dataclasses import replace

    s.hold_at(tuple(cur["joints_rad"]))
    image_from_voxel = world.scan1.image_from_voxel.copy()
    image_from_voxel[0, 3] += 2.0
    uid, _ = s.export(replace(world.scan1, image_from_voxel=image_from_voxel), "knocked")
    v = s.client.post("/verify", json={"scan_id": s.scan(uid)["id"]})
    s.hold_at(h.Q1)
    assert v.status_code == 200 and not v.json()["passed"], v.text
    b = p.locator("#withdrawn-banner")
    b.wait_for()
    text = b.text_content()
    assert f"Registration {cur['id']} was withdrawn: verification {v.json()['id']}" in text, text
    # issue 40 item 4: at the registration's own joints the chain cannot explain it (on main: "cell not
    # calibrated", a 22-scan calibration, although the phantom was knocked)
    assert "Likely cause: phantom knocked or O-arm moved" in text, text
    assert "What to do: Check the phantom" in text, text
    assert b.get_attribute("data-cause") == "phantom-or-oarm-moved"
    assert p.is_visible("#current-none") and p.text_content("#current-badge") == "none"
    assert s.client.get("/registration/current").status_code == 409
    _current(s)  # leave a current registration for the other tests
    assert_clean(w, provoked=WITHDRAWN)


def test_the_page_speaks_to_or_staff(
    context: Any, svc: tuple[h.Service, dict[str, Any]], world: h.World
) -> None:
    """Issue 42, item 5 (at 1400 px, the context's viewport): the headline figure with its gate and a
    one-word verdict that also colours the badge and the warning; one sentence per fact; actions
    without API words (those in a tooltip); a scan's "why" readable in a few lines; after a failed
    verification its banner, verdict, histogram and action together at the top."""
    s, _ = svc
    cur = _current(s)
    w = _showing(context, s, cur["id"])
    p = w.page
    gate = s.client.get("/status").json()["gates"]["max_verification_error_mm"]
    chain = cur["expected_error"]["predicted_chain_error_mm"]
    assert float(p.get_attribute("#current-gate", "data-value")) == gate
    verdict = p.text_content("#current-verdict")
    assert verdict == ("FAIL" if chain >= gate else "OK")
    cls = p.get_attribute("#current-verdict", "class").split()[-1]
    assert p.get_attribute("#current-badge", "class").split()[-1] == cls  # one verdict, one colour
    assert p.get_attribute("#current-uncalibrated", "class") == cls
    expected = p.text_content("#current-expected")
    assert expected.count("not calibrated") == 1, expected  # one sentence per fact
    # the moved scan's reason: a few lines at 1400 px, not one word a line
    why = p.locator("#scans-body td.why:has-text('robot moved')").first
    line_px = float(p.evaluate("parseFloat(getComputedStyle(document.body).lineHeight)"))
    box = _box(why)
    assert box["height"] <= 3 * line_px + 2, box
    # a failed verification: the scan at the registration's pose, the link reporting J6 turned (from
    # the registration's own joints: at the same joints the cause would be the phantom, issue 40)
    q_reg = cur["joints_rad"]
    s.hold_at((*q_reg[:5], q_reg[5] + 0.04))
    uid, _ = s.export(world.scan1, "wrong-pose-42")
    failed = s.client.post("/verify", json={"scan_id": s.scan(uid)["id"]}).json()
    s.hold_at(h.Q1)
    assert not failed["passed"]
    p.wait_for_selector(f"#alarm-title[data-verification='{failed['id']}']")
    alarm = p.locator("#alarm")
    assert p.evaluate("document.getElementById('app').firstElementChild.id") == "alarm"
    box = _box(alarm)
    assert box["y"] < 400 and box["y"] + box["height"] < 1000, box  # on the first screen
    text = alarm.text_content()
    assert "What to do:" in text and "FAILED" in text and alarm.locator("svg line.gate").count() == 1
    assert "POST /" not in p.inner_text("#app"), "an API call left in the page's words"
    assert "POST /calibrations" in (alarm.locator("abbr.api").first.get_attribute("title") or "")
    _current(s)  # leave a current registration for the other tests
    assert_clean(w, provoked=WITHDRAWN)  # the withdrawal this test causes may race the page's own GET


def test_the_self_hosted_docs_send_the_token(context: Any, svc: tuple[h.Service, dict[str, Any]]) -> None:
    s, _ = svc
    w = _signed_in(context, s)
    spec: list[Any] = []
    w.page.on("request", lambda req: spec.append(req) if req.url.endswith("/openapi.json") else None)
    w.page.click("#docs-link")
    w.page.wait_for_selector(".opblock-summary-path[data-path='/registration/current']")
    assert spec and spec[0].headers.get("authorization") == f"Bearer {h.TOKEN}"
    assert_clean(w)


def test_a_navigation_ui_on_another_origin_uses_the_api_through_cors(
    context: Any, svc: tuple[h.Service, dict[str, Any]], nav_ui: Any
) -> None:
    s, _ = svc
    cur = _current(s)
    page = context.new_page()
    page.goto(f"{nav_ui.base_url}/?api={s.base_url}#{h.TOKEN}")
    page.wait_for_function("document.body && (document.body.dataset.result || document.body.dataset.error)")
    assert page.evaluate("document.body.dataset.error") is None
    result = json.loads(page.evaluate("document.body.dataset.result"))
    assert result["anonymous_status"] == 401  # readable (CORS headers on the 401), still refused
    assert result["status"] == 200 and result["body"]["id"] == cur["id"]
    assert result["body"]["fre_mm"] == cur["fre_mm"]
    pre = httpx.options(
        s.base_url + "/registration/current",
        headers={"Origin": nav_ui.base_url, "Access-Control-Request-Method": "GET",
                 "Access-Control-Request-Headers": "authorization"},
    )  # fmt: skip
    assert pre.status_code == 200 and pre.headers["access-control-allow-origin"] == nav_ui.base_url


def _doc_table(text: str, heading: str) -> dict[str, str]:
    """First-column `code` → second column of the first table after ``heading`` in docs/slicer.md."""
    section = text.split(heading, 1)[1]
    rows = {}
    for line in section.splitlines():
        if line.startswith("| `"):
            cells = [c.strip() for c in line.strip("|").split("|")]
            rows[cells[0].strip("`")] = cells[1]
        elif rows and not line.startswith("|"):
            break
    return rows


def test_slicer_doc_matches_what_pyigtl_receives(svc: tuple[h.Service, dict[str, Any]]) -> None:
    """docs/slicer.md: the device names, the RAS conversion and the metadata keys, against the
    service's OpenIGTLink server with pyigtl (what Slicer's Python tools use) as the client."""
    import numpy as np
    import pyigtl

    from tests.integration.polling import poll_until

    s, _ = svc
    cur = _current(s)
    text = (h.REPO / "docs" / "slicer.md").read_text()
    devices = _doc_table(text, "## 2. Connect Slicer")
    keys = _doc_table(text, "## 3. Metadata")
    assert set(devices) == {"RobotToImage", "ToolToImage"}
    port = s.client.get("/status").json()["listeners"]["igtl"]["port"]
    client = pyigtl.OpenIGTLinkClient(host="127.0.0.1", port=port)
    # as Slicer does at connect: a version-2 message, so the server answers with version-2 headers
    # and the metadata (docs/or-integration.md, header version per client)
    hello = pyigtl.StringMessage("reads header version 2", device_name="Hello")
    hello.header_version = 2
    client.send_message(hello, wait=False)
    try:
        got = {}
        for device in devices:
            got[device] = poll_until(
                lambda d=device: (
                    (m := client.wait_for_message(d, timeout=0.2)) is not None
                    and m.metadata.get("TransformStatus") == "OK"
                    and m.metadata.get("RegistrationId") == str(cur["id"])
                    and m
                ),
                f"{device} of registration {cur['id']}",
                timeout_s=20,
            )
    finally:
        client.stop()
    ras_from_lps = np.diag([-1.0, -1.0, 1.0, 1.0])
    robot_to_image = got["RobotToImage"]
    np.testing.assert_allclose(
        robot_to_image.matrix, ras_from_lps @ np.asarray(cur["image_from_robot"]), atol=1e-4
    )
    for device, msg in got.items():
        undocumented = set(msg.metadata) - set(keys)
        assert not undocumented, f"{device} sends metadata docs/slicer.md does not list: {undocumented}"
        assert msg.metadata["ImageFrame"] == "RAS"
    assert (
        got["RobotToImage"].metadata["SourceFrame"] == "robot"
        and got["ToolToImage"].metadata["SourceFrame"] == "tcp"
    )
    for key in ("FRE_mm", "TRE_pred_mm", "RegistrationId", "TransformStatus"):
        assert key in robot_to_image.metadata, key
    assert float(robot_to_image.metadata["FRE_mm"]) == pytest.approx(cur["fre_mm"], rel=1e-5)
