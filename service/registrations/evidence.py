"""What backs a registration's robot side: its evidence level (docs/safety.md, "Evidence levels").

One scan cannot see an error on the robot side (the robot model, the rod, the mount): every sphere
moves together, the fit absorbs it, and FRE stays small — a rod typed in radians registered with an
FRE of 0.027 mm and served a matrix 176–275 mm wrong 150 mm from the phantom.  So every registration
states what backs the robot side, strongest first:

* ``calibrated``: an active calibration made under the same robot settings backs it (the settings
  binding of :mod:`service.registrations.robot_side` withdraws a registration whose calibration or
  settings changed), with the calibration's predicted error at the working poses;
* ``verified``: a verification scan at another pose passed against it;
* ``unverified``: neither — the nominal model and the configured rod.  Still served (the operating
  room decides), but it says so first, with the action.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

from service.records import RegistrationRecord

EvidenceLevel = Literal["calibrated", "verified", "unverified"]
EVIDENCE_LEVELS: tuple[EvidenceLevel, ...] = ("calibrated", "verified", "unverified")

UNVERIFIED_ACTION = (
    "verify at another pose (move the shoulder and elbow, scan the phantom, verify), or calibrate the cell"
)


@dataclass(frozen=True)
class Evidence:
    """A registration's evidence level, one sentence saying what it rests on, and the action
    (empty when none is needed)."""

    level: EvidenceLevel
    summary: str
    action: str = ""


def calibration_of(provenance: dict[str, Any]) -> tuple[int | None, dict[str, Any]]:
    """The id of the calibration a registration was made through (None: the nominal model) and its
    provenance entry (empty without one)."""
    cal = provenance.get("calibration")
    if not isinstance(cal, dict) or cal.get("calibration_id") is None:
        return None, {}
    return int(cal["calibration_id"]), cal


def evidence_of(rec: RegistrationRecord) -> Evidence | None:
    """The evidence level of an accepted (or once accepted) registration; None without figures."""
    fig = rec.figures
    if fig is None:
        return None
    cal_id, cal = calibration_of(fig.provenance)
    if cal_id is not None:
        err = cal.get("predicted_chain_error_mm")
        figure = (
            f", predicted error {float(err):.2f} mm at the working poses"
            if isinstance(err, int | float)
            else ""
        )
        return Evidence("calibrated", f"Calibration {cal_id} backs the robot side{figure}.")
    if rec.verified_by is not None:
        return Evidence(
            "verified", f"A verification at another pose (verification {rec.verified_by}) passed against it."
        )
    return Evidence(
        "unverified",
        "One scan cannot see an error in the robot model, rod or mount, and no scan at another pose has "
        "checked this matrix.",
        UNVERIFIED_ACTION,
    )
