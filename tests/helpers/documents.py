"""What the documents the project writes must hold, shared by the tests that check them."""

from __future__ import annotations

from typing import Final

REGISTRATION_DOC_KEYS: Final = (
    "image_from_robot",
    "fre_mm",
    "fle_mm",
    "n_expected",
    "n_detected",
    "n_matched",
    "spheres",
    "predicted_tre_mm",
    "symmetry_margin",
    "timings_s",
    "provenance",
)
"""Keys of a registration's JSON (``RegistrationResult.to_dict``, ``oarmreg register --out``)."""
