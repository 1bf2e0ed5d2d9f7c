"""What every centre estimator is given, what it must provide, and the lookup by name.

:class:`MeasuredSphere` is the detection's record of one sphere at the moment its centre is
estimated; :class:`CentreEstimator` the two steps an estimator provides; :func:`centre_estimator`
imports the estimator a detection names (:data:`registration.detection.estimators.ESTIMATOR_MODULES`).
:class:`SpherePatch` is the raw voxels around a sphere, for the estimators that look at them.
"""

from __future__ import annotations

import functools
import importlib
import math
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar, cast

import numpy as np
from numpy.typing import NDArray

from registration.arrays import F64
from registration.detection.candidates import Support
from registration.detection.centroid import SATURATION_MIN_VOXELS
from registration.detection.cross_check import SliceCircle
from registration.detection.estimators import ESTIMATOR_MODULES, METHODS
from registration.detection.fov import near_imaged_edge
from registration.detection.params import DetectionParams
from registration.errors import DetectionError

PreparedT = TypeVar("PreparedT")


@dataclass(frozen=True, eq=False)
class MeasuredSphere:
    """One sphere as the detection has measured it when its centre is estimated.

    ``vox`` the whole volume (k, j, i), ``spacing`` (i, j, k) mm, ``fov_radius_mm`` the circular
    FOV (None: none found); ``centre_ijk`` the sub-voxel centroid, edge-refined; ``saturation_hu``
    the value the centroid's ball is clipped at (inf if it is not); ``support`` a split core's
    region (None for an unsplit blob); ``circles`` the accepted circle per slice and
    ``radius_fit_mm`` the radius fitted to them (NaN below two slices); ``dz_mm`` the slice spacing.
    """

    vox: NDArray[Any]
    spacing: F64
    fov_radius_mm: float | None
    centre_ijk: F64
    saturation_hu: float
    support: Support | None
    circles: list[SliceCircle]
    radius_fit_mm: float
    dz_mm: float
    params: DetectionParams

    def near_edge(self) -> bool:
        """Whether an edge of the imaged region (slab end, matrix edge, FOV circle) is within
        ``radius + bloom + background_shell`` of the centre: a patch of that reach is cut or
        holds padding there."""
        p = self.params
        vox = self.vox
        shape = (vox.shape[0], vox.shape[1], vox.shape[2])
        reach_mm = p.radius_mm + p.bloom_mm + p.background_shell_mm
        return near_imaged_edge(self.centre_ijk, shape, self.spacing, self.fov_radius_mm, reach_mm)


class CentreEstimator(Protocol[PreparedT]):
    """A centre estimator: ``prepare`` gathers what it looks at into its own record, ``estimate``
    turns that into the centre (i, j, k) or ``(None, why not)``.

    ``circles_are_the_measurement``: the estimator measures the centre from the slice circles,
    so MAR runs on every slice patch before the circle test (Bai 2018), not only where the raw
    cross-section fails it.
    """

    circles_are_the_measurement: bool

    def prepare(self, sphere: MeasuredSphere) -> PreparedT: ...

    def estimate(self, prepared: PreparedT) -> tuple[F64 | None, str]: ...


@functools.cache
def centre_estimator(method: str) -> CentreEstimator[Any]:
    """The estimator named ``method``, its module imported on first use."""
    if method not in ESTIMATOR_MODULES:
        raise DetectionError(f"unknown detection method {method!r}: expected one of {', '.join(METHODS)}")
    return cast("CentreEstimator[Any]", importlib.import_module(ESTIMATOR_MODULES[method]).ESTIMATOR)


@dataclass(frozen=True, eq=False)
class SpherePatch:
    """The raw voxels around one sphere, for estimators that look at intensities (``model``, ``core``).

    ``values_hu`` (V,) and ``coords_mm`` (V, 3) = voxel index (i, j, k) × spacing; ``spacing_mm``
    (i, j, k); ``saturation_hu`` (inf if the crop is not clipped); ``radius_mm`` nominal.
    """

    values_hu: F64
    coords_mm: F64
    spacing_mm: F64
    saturation_hu: float
    radius_mm: float


def sphere_patch(vox: NDArray[Any], centre_ijk: F64, spacing: F64, params: DetectionParams) -> SpherePatch:
    """Voxels within ``radius + bloom + background_shell`` mm of ``centre_ijk`` (clamped to the volume)."""
    r_out = params.radius_mm + params.bloom_mm + params.background_shell_mm
    half = np.ceil(r_out / spacing).astype(int) + 1
    c = np.rint(centre_ijk).astype(int)
    lo = np.maximum(c - half, 0)
    hi = np.minimum(c + half + 1, (vox.shape[2], vox.shape[1], vox.shape[0]))
    crop = np.asarray(vox[lo[2] : hi[2], lo[1] : hi[1], lo[0] : hi[0]], dtype=np.float64)
    kk, jj, ii = np.meshgrid(
        np.arange(lo[2], hi[2]), np.arange(lo[1], hi[1]), np.arange(lo[0], hi[0]), indexing="ij"
    )
    coords = np.stack([ii.ravel(), jj.ravel(), kk.ravel()], axis=1).astype(np.float64) * spacing
    keep = np.sum((coords - centre_ijk * spacing) ** 2, axis=1) <= r_out**2
    values = crop.ravel()[keep]
    peak = float(values.max()) if len(values) else math.nan
    saturated = len(values) > 0 and int(np.count_nonzero(values == peak)) >= SATURATION_MIN_VOXELS
    return SpherePatch(values, coords[keep], spacing, peak if saturated else math.inf, params.radius_mm)
