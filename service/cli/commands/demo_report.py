"""What ``oarmreg demo`` and ``demo --calibrate`` print about a registration and a withdrawal:
the honest figure first, and a failed verification's withdrawal in plain words.  Shared by
:mod:`service.cli.commands.demo` and :mod:`service.cli.commands.demo_calibrate` (which must not import
demo)."""

from __future__ import annotations

import sys
from typing import Any


def out(msg: str = "") -> None:
    sys.stdout.write(msg + "\n")
    sys.stdout.flush()


def expected_error_lines(reg: dict[str, Any]) -> str:
    """The honest figure first: the expected error at the robot's working poses and
    whether a calibration backs it, then the one-scan TRE labelled as what it is."""
    e = reg.get("expected_error") or {}
    chain = e.get("predicted_chain_error_mm", reg.get("predicted_chain_error_mm"))
    chain_text = "unknown" if chain is None else f"{chain:.2f} mm"
    if e.get("calibrated"):
        backing = f"calibration {e.get('calibration_id')} backs it"
    else:
        backing = "the cell is NOT calibrated: the nominal model's prior"
    tre = e.get("one_scan_tre_max_mm")
    one_scan = "" if tre is None else f"; one-scan TRE, this pose only: max {tre:.4f} mm"
    expected = f"expected error at the robot's working poses: {chain_text} ({backing}){one_scan}"
    return f"{evidence_line(reg)}\n{expected}"


def evidence_line(reg: dict[str, Any]) -> str:
    """What backs the robot side, first (docs/safety.md, "Evidence levels")."""
    ev = reg.get("evidence") or {}
    level = str(ev.get("level", "unverified")).upper()
    action = f" Next: {ev['action']}." if ev.get("action") else ""
    return f"evidence: {level}: {ev.get('summary', '')}{action}"


def report_withdrawal(client: Any, ver: dict[str, Any]) -> None:
    """A failed verification withdrew the registration: say so plainly, with the service's likely
    cause and action (docs/safety.md, "Which registration may be current")."""
    r = client.get("/registration/current")
    if r.status_code == 200:
        return
    body = r.json()
    out(
        f"  registration {ver['registration_id']} is WITHDRAWN: the service serves no registration now "
        "(/registration/current 409, /ready 503, OpenIGTLink INVALID)"
    )
    if body.get("likely_cause"):
        w = body.get("withdrawal") or {}
        out(f"  likely cause ({body['likely_cause']}): {w.get('cause', '')}")
        out(f"  what to do: {body.get('action', '')}")
