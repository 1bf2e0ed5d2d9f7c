"""The reconstructed volume of a series as the planner and the calibration need it.

:class:`SeriesGeometry` is what ``oarmreg register`` writes into its JSON and the service into
its registration record: the ImagePositionPatient range (first and last slice), the orientation
(ImageOrientationPatient row / column directions and the slice normal), rows / columns / slices,
pixel and slice spacing, and the FOV circle (the largest circle inside the in-plane square, about
its centre — the O-arm reconstructs a disk, research/calibration.md §4).
:meth:`SeriesGeometry.scan_volume` is that volume as the planner's / calibration's cylinder
(:class:`registration.calibration.planner.ScanVolume`) in the image frame.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from registration.errors import SeriesGeometryError

if TYPE_CHECKING:
    from registration.calibration.planner import ScanVolume
    from registration.imaging.volume import Volume

Vec3 = tuple[float, float, float]


def _vec(v: Any, name: str) -> Vec3:
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise SeriesGeometryError(f"series_geometry.{name} must be 3 finite numbers, got {v!r}")
    return (float(a[0]), float(a[1]), float(a[2]))


@dataclass(frozen=True)
class SeriesGeometry:
    """A series' voxel grid in the image frame (LPS, mm)."""

    first_position_mm: Vec3
    """ImagePositionPatient of the first slice (centre of its first pixel)."""
    last_position_mm: Vec3
    row_direction: Vec3
    """ImageOrientationPatient[0:3]: direction of increasing column index i."""
    column_direction: Vec3
    """ImageOrientationPatient[3:6]: direction of increasing row index j."""
    rows: int
    columns: int
    n_slices: int
    pixel_spacing_mm: tuple[float, float]
    """(along a row = between columns, along a column = between rows)."""
    slice_spacing_mm: float
    fov_radius_mm: float
    """Radius of the FOV circle: half the shorter in-plane extent."""

    @property
    def slice_normal(self) -> Vec3:
        n = np.cross(self.row_direction, self.column_direction)
        n /= np.linalg.norm(n)
        return (float(n[0]), float(n[1]), float(n[2]))

    @property
    def centre_image_mm(self) -> Vec3:
        r, c = np.asarray(self.row_direction), np.asarray(self.column_direction)
        half = 0.5 * (
            (self.columns - 1) * self.pixel_spacing_mm[0] * r + (self.rows - 1) * self.pixel_spacing_mm[1] * c
        )
        mid = 0.5 * (np.asarray(self.first_position_mm) + np.asarray(self.last_position_mm)) + half
        return (float(mid[0]), float(mid[1]), float(mid[2]))

    @property
    def half_length_mm(self) -> float:
        """Half the axial coverage: slice centres span (n − 1) × spacing, plus half a slice each end."""
        return 0.5 * self.n_slices * self.slice_spacing_mm

    def scan_volume(self) -> ScanVolume:
        from registration.calibration.planner import ScanVolume

        return ScanVolume(self.centre_image_mm, self.fov_radius_mm, self.half_length_mm, self.slice_normal)

    def to_dict(self) -> dict[str, Any]:
        return {
            "image_position_first_mm": list(self.first_position_mm),
            "image_position_last_mm": list(self.last_position_mm),
            "image_orientation": list(self.row_direction) + list(self.column_direction),
            "rows": self.rows,
            "columns": self.columns,
            "n_slices": self.n_slices,
            "pixel_spacing_mm": list(self.pixel_spacing_mm),
            "slice_spacing_mm": self.slice_spacing_mm,
            "fov_radius_mm": self.fov_radius_mm,
            "fov_centre_image_mm": list(self.centre_image_mm),
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> SeriesGeometry:
        """Parse :meth:`to_dict`'s form; :class:`SeriesGeometryError` naming the bad field."""
        try:
            orient = [float(v) for v in d["image_orientation"]]
            if len(orient) != 6:
                raise SeriesGeometryError("series_geometry.image_orientation must have 6 numbers")
            ps = [float(v) for v in d["pixel_spacing_mm"]]
            if len(ps) != 2 or min(ps) <= 0:
                raise SeriesGeometryError("series_geometry.pixel_spacing_mm must be 2 positive numbers")
            g = cls(
                _vec(d["image_position_first_mm"], "image_position_first_mm"),
                _vec(d["image_position_last_mm"], "image_position_last_mm"),
                _vec(orient[:3], "image_orientation"),
                _vec(orient[3:], "image_orientation"),
                int(d["rows"]),
                int(d["columns"]),
                int(d["n_slices"]),
                (ps[0], ps[1]),
                float(d["slice_spacing_mm"]),
                float(d["fov_radius_mm"]),
            )
        except (KeyError, TypeError, ValueError) as e:
            raise SeriesGeometryError(
                f"series_geometry is malformed ({type(e).__name__}: {e}); "
                "rerun `oarmreg register` to write it"
            ) from None
        if min(g.rows, g.columns, g.n_slices) < 1 or g.slice_spacing_mm <= 0 or g.fov_radius_mm <= 0:
            raise SeriesGeometryError("series_geometry: rows, columns, slices and spacings must be positive")
        return g


def series_geometry(volume: Volume) -> SeriesGeometry:
    """The geometry of a loaded :class:`~registration.imaging.volume.Volume`."""
    m = volume.image_from_voxel
    sp = volume.spacing_mm
    n_slices, rows, cols = volume.shape
    first = m[:3, 3]
    last = m[:3, 3] + (n_slices - 1) * m[:3, 2]
    r = m[:3, 0] / sp[0]
    c = m[:3, 1] / sp[1]
    fov = 0.5 * min(cols * float(sp[0]), rows * float(sp[1]))
    return SeriesGeometry(
        _vec(first, "first"),
        _vec(last, "last"),
        _vec(r, "row"),
        _vec(c, "column"),
        rows,
        cols,
        n_slices,
        (float(sp[0]), float(sp[1])),
        float(sp[2]),
        fov,
    )
