"""``make screenshots``: the status page and ``/docs`` in headless Chromium, as PNGs in docs/img/.

The same service and history as the browser tests (mock controller, simulated scans): an accepted
registration, a refusal, a passed verification; then a failed one, which withdraws the registration
(``page-withdrawn.png``).  Not a test; look at the pictures.

    python -m tests.browser.screenshots docs/img
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

from tests.browser import harness as h

VIEWPORT = {"width": 1400, "height": 900}
QUOTA_MB = 2048.0
"""A retention quota for the status panel's disk line (nothing near it is used)."""


def main(argv: list[str]) -> int:
    from registration.io.resources import default_phantom
    from registration.model.phantom import load_phantom

    out = Path(argv[0] if argv else "docs/img")
    out.mkdir(parents=True, exist_ok=True)
    reason = h.chromium_missing()
    if reason is not None:
        print(f"screenshots: {reason}", file=sys.stderr)
        return 3
    world = h.make_world(load_phantom(default_phantom()))
    with (
        tempfile.TemporaryDirectory(prefix="oarmreg-shots-") as tmp,
        h.running_service(Path(tmp), world, **{"retention.max_disk_mb": QUOTA_MB}) as svc,
    ):
        h.build_history(svc, world)
        with h.browser() as b:
            ctx = b.new_context(viewport=VIEWPORT, device_scale_factor=1)
            p = ctx.new_page()
            p.goto(f"{svc.base_url}/#token={h.TOKEN}")
            p.wait_for_selector("#live.ok")
            p.wait_for_selector("#current-id:not(:empty)")
            shoot(p, out, {"page-overview.png": None, "page-current-registration.png": "#current",
                           "page-status.png": "#status"})  # fmt: skip
            # a failed verification: the link reports J6 turned; it withdraws the registration
            q = (*h.Q1[:5], h.Q1[5] + 0.04)
            svc.hold_at(q)
            uid, _ = svc.export(world.scan1, "wrong-pose")
            failed = svc.client.post("/verify", json={"scan_id": svc.scan(uid)["id"]}).json()
            svc.hold_at(h.Q1)
            p.wait_for_selector("#withdrawn-banner", state="visible")
            p.locator(f"#verifications-body tr[data-verification='{failed['id']}']").click()
            p.wait_for_selector("#ver-title[data-verdict='FAIL']")
            shoot(p, out, {"page-withdrawn.png": None, "page-verification.png": "#verifications"})
            p.click("#docs-link")
            p.wait_for_selector(".opblock")
            p.screenshot(path=out / "page-docs.png")
            print(out / "page-docs.png")
            ctx.close()
    return 0


def shoot(p: object, out: Path, shots: dict[str, str | None]) -> None:
    """Each named PNG: the whole page (``None``) or the element the selector names."""
    for name, selector in shots.items():
        if selector is None:
            p.evaluate("window.scrollTo(0, 0)")  # type: ignore[attr-defined]
            p.screenshot(path=out / name, full_page=True)  # type: ignore[attr-defined]
        else:
            p.locator(selector).screenshot(path=out / name)  # type: ignore[attr-defined]
        print(out / name)


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
