"""The :class:`Volume`: voxels plus their exact voxel → image (LPS, mm) geometry."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from registration.model import frames


@dataclass(frozen=True, eq=False)
class Volume:
    """A CT volume in Hounsfield units with its geometry.

    Attributes
    ----------
    voxels : ndarray, shape (n_slices, rows, columns)
        HU values, indexed ``voxels[k, j, i]``: k = slice (sorted along the
        slice normal, increasing position), j = row, i = column.  int16 when
        the DICOM rescale is integral (the usual case), else float32.
    image_from_voxel : ndarray, shape (4, 4), float64
        Maps the homogeneous index vector ``(i, j, k, 1)`` (column, row,
        slice) to DICOM patient coordinates (LPS, mm), built from
        ImagePositionPatient (0020,0032) (centre of the first pixel),
        ImageOrientationPatient (0020,0037), PixelSpacing (0028,0030) and the
        slice positions (never SliceThickness).
    series_uid : str
        SeriesInstanceUID (0020,000E).
    frame_of_reference_uid : str
        FrameOfReferenceUID (0020,0052).
    meta : mapping
        Provenance: file paths in slice order, acquisition date/time, etc.
    """

    voxels: NDArray[Any]
    image_from_voxel: NDArray[np.float64]
    series_uid: str = ""
    frame_of_reference_uid: str = ""
    meta: Mapping[str, Any] = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int, int]:
        s = self.voxels.shape
        return (int(s[0]), int(s[1]), int(s[2]))

    @property
    def spacing_mm(self) -> NDArray[np.float64]:
        """Voxel size along (i, j, k) = (column, row, slice) in mm."""
        return np.asarray(np.linalg.norm(self.image_from_voxel[:3, :3], axis=0), dtype=np.float64)

    def voxel_to_image(self, ijk: NDArray[Any]) -> NDArray[np.float64]:
        """(N, 3) continuous (i, j, k) indices → (N, 3) LPS mm."""
        return frames.apply(self.image_from_voxel, ijk)

    def image_to_voxel(self, points_image_mm: NDArray[Any]) -> NDArray[np.float64]:
        """(N, 3) LPS mm → (N, 3) continuous (i, j, k) indices."""
        return frames.apply(np.linalg.inv(self.image_from_voxel), points_image_mm)
