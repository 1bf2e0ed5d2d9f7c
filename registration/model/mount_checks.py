"""Is a flange-mounted transform (the rod ``tool0_from_phantom``, the tool ``tool0_from_tcp``)
plausible in the units its fields claim?

A one-scan registration cannot see an error on the robot side: with a rod typed in radians in a
degrees field (``rpy_deg = [3.14159, 0, 0]``, meant as 180°) every sphere moves together, the fit
absorbs it, FRE stays at a few hundredths of a millimetre, and robot points 150 mm from the phantom
land 176–275 mm from where they belong.  These checks catch the unit slips a
person makes when copying a rod's values from a CAD tool or a pendant, and let real odd mounts pass:

* **radians in a degrees field**: every non-zero angle is within :data:`RADIAN_MATCH_TOL` of a
  non-zero multiple of π/4 (0.7854, 1.5708, 3.1416, …, read as radians) and none exceeds 2π.  A real
  rod in degrees is 0/90/180 or a deliberate angle; a value like 3.1416° or 1.5708° is a radian
  typed in the wrong field, and a mix with any ordinary degree value (12.5, 90) passes.
* **metres in a millimetre field** (the rod only): the phantom's centre lies closer to the flange
  than the phantom's own smallest half-size, so the flange would be inside the phantom.  That
  catches ``[0, 0, 0.2]`` (0.2 m typed for 200 mm) and a rod left at zero.
* **beyond the arm's reach** (the rod only): farther than :data:`MAX_ROD_LENGTH_MM`.

Each check returns a sentence naming the field, the value, the likely unit and the fix; an empty list
means plausible.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

RADIAN_MATCH_TOL = 0.002
"""How close (in the field's number) an angle must be to a multiple of π/4 to read as radians: wide
enough for ``3.14`` and ``1.57`` (0.0016 and 0.0008 off), narrow enough that a degree value of a real
mount (integers, halves, tenths) never falls inside except 3.14, 1.57 themselves."""

MAX_ROD_LENGTH_MM = 670.0
"""Longest flange-to-phantom-centre distance accepted: the TX60's and TX2-60's reach, 670 mm (Stäubli
TX60 / TX2-60 data sheets; the URDFs' shoulder-to-flange chain, 0.29 + 0.31 + 0.07 m).  A rod as long
as the arm itself would hang a 1 kg phantom on a lever that doubles the wrist's load beyond its rated
payload inertia and would put the phantom out of the O-arm's bore at every reachable pose: a length
beyond it is a unit slip (cm typed as mm) or a typo."""


def radian_like_rpy(rpy: Sequence[float]) -> bool:
    """True when the non-zero angles of ``rpy`` all look like radians: each within
    :data:`RADIAN_MATCH_TOL` of a non-zero multiple of π/4, none beyond 2π."""
    nonzero = [float(a) for a in rpy if abs(float(a)) > 1e-9]
    if not nonzero or any(abs(a) > 2 * math.pi + RADIAN_MATCH_TOL for a in nonzero):
        return False
    quarter = math.pi / 4
    for a in nonzero:
        k = round(a / quarter)
        if k == 0 or abs(a - k * quarter) > RADIAN_MATCH_TOL:
            return False
    return True


def rpy_problems(setting: str, rpy_deg: Sequence[float]) -> list[str]:
    """The radians-in-degrees check of one ``rpy_deg`` field (``setting`` names it)."""
    if not radian_like_rpy(rpy_deg):
        return []
    as_deg = [round(math.degrees(float(a)), 1) for a in rpy_deg]
    return [
        f"{setting}.rpy_deg = {list(rpy_deg)} looks like radians in a degrees field (read as radians: "
        f"{as_deg}°): enter degrees, e.g. rpy_deg = {as_deg}"
    ]


def rod_length_problems(
    setting: str, translation_mm: Sequence[float], phantom_min_half_size_mm: float
) -> list[str]:
    """The rod's length against the phantom's smallest half-size and the arm's reach."""
    length = math.sqrt(sum(float(c) ** 2 for c in translation_mm))
    if length < phantom_min_half_size_mm:
        hint = (
            f" — it looks like metres: {[round(float(c) * 1000.0, 1) for c in translation_mm]} mm?"
            if 0 < length < 1.0
            else ""
        )
        return [
            f"{setting}.translation_mm = {list(translation_mm)} puts the phantom's centre {length:.3g} mm "
            f"from the flange, closer than the phantom's own half-size ({phantom_min_half_size_mm:g} mm): "
            f"the flange would be inside the phantom{hint}; enter the rod's length in millimetres"
        ]
    if length > MAX_ROD_LENGTH_MM:
        return [
            f"{setting}.translation_mm = {list(translation_mm)} puts the phantom {length:.0f} mm from the "
            f"flange, beyond the arm's own reach ({MAX_ROD_LENGTH_MM:g} mm, TX60/TX2-60): check the unit "
            f"(millimetres) and the rod's drawing"
        ]
    return []
