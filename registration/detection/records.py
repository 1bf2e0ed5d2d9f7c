"""What the detection returns: the spheres found, the candidates rejected and why, per-stage times.

These records are the detection's boundary: the service, the CLI (``oarmreg detect --json``) and
the registration read them; nothing of the detection's internals leaks past them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from registration.arrays import F64


@dataclass(frozen=True, eq=False)
class DetectedSphere:
    """One detected sphere.

    Attributes
    ----------
    center_image_mm : ndarray, shape (3,), float64
        Centre in the image frame (DICOM LPS, mm).
    radius_mm : float
        Per-sphere fitted radius from the circle radii (r_i² + z_i² = c + 2·z0·z_i);
        this is the *apparent* (bloomed) radius, typically 1.5–2 mm for a
        1.25 mm steel sphere.  NaN if fewer than two circle slices.
    n_slices : int
        Slices with an accepted circle.
    score : float
        0 … 1: fraction of the blob's slices with an accepted circle × (1 −
        in-plane disagreement between the circles and the centre / radius).
    center_voxel : ndarray, shape (3,), float64
        Centre in continuous voxel indices (i, j, k).
    """

    center_image_mm: F64
    radius_mm: float
    n_slices: int
    score: float
    center_voxel: F64 = field(default_factory=lambda: np.full(3, math.nan))


@dataclass(frozen=True)
class Rejection:
    """A bright blob that is not reported as a sphere, and why."""

    center_image_mm: tuple[float, float, float]
    reason: str


@dataclass(frozen=True, eq=False)
class FaceOffset:
    """The phantom's face offset β of one scan, fitted over the phantom's hole grid.

    Attributes
    ----------
    beta_mm : float
        Shared offset of every detected centre along its hole's outward axis, mm (negative: the
        centres sit deeper in their holes than the phantom file says).
    beta_se_mm : float
        Its least-squares standard error, mm (NaN if undetermined).
    centres_image_mm : ndarray, shape (M, 3), float64
        The detected centres with β · n_i removed, image frame (LPS, mm), detection order; NaN
        rows for detections paired with no hole.
    """

    beta_mm: float
    beta_se_mm: float
    centres_image_mm: F64

    def to_dict(self) -> dict[str, float | None]:
        return {
            "face_offset_mm": float(self.beta_mm),
            "face_offset_se_mm": None if math.isnan(self.beta_se_mm) else float(self.beta_se_mm),
        }


@dataclass(frozen=True, eq=False)
class DetectionResult:
    """Spheres found in one volume, the rejected candidates and the time spent per stage.

    ``face_offset`` is None until a caller that knows the phantom fits it
    (:func:`registration.matching.face_offset_grid.grid_face_offset`); ``face_offset_reason`` then says
    why it could not be fitted, if it could not.
    """

    spheres: tuple[DetectedSphere, ...]
    rejections: tuple[Rejection, ...]
    method: str
    timings_s: dict[str, float]
    face_offset: FaceOffset | None = None
    face_offset_reason: str = ""

    @property
    def centres_image_mm(self) -> F64:
        """(M, 3) float64 sphere centres, image frame (LPS, mm), in detection order."""
        if not self.spheres:
            return np.zeros((0, 3))
        return np.stack([s.center_image_mm for s in self.spheres]).astype(np.float64)

    def to_dict(self, series_uid: str = "") -> dict[str, Any]:
        """The ``oarmreg detect --json`` document."""
        fo = self.face_offset
        doc = self._base_dict(series_uid)
        if fo is not None:
            doc.update(fo.to_dict())
            for s, c in zip(doc["spheres"], fo.centres_image_mm, strict=True):
                s["center_corrected_mm"] = None if np.isnan(c).any() else [float(v) for v in c]
        elif self.face_offset_reason:
            doc["face_offset_mm"] = None
            doc["face_offset_reason"] = self.face_offset_reason
        return doc

    def _base_dict(self, series_uid: str) -> dict[str, Any]:
        return {
            "series_uid": series_uid,
            "frame": "image",
            "method": self.method,
            "spheres": [
                {
                    "center_mm": [float(v) for v in s.center_image_mm],
                    "radius_mm": None if math.isnan(s.radius_mm) else float(s.radius_mm),
                    "n_slices": int(s.n_slices),
                    "score": float(s.score),
                }
                for s in self.spheres
            ],
            "rejected": [{"center_mm": list(r.center_image_mm), "reason": r.reason} for r in self.rejections],
            "timings_s": dict(self.timings_s),
        }
