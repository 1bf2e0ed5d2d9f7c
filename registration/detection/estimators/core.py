"""The ``core`` estimator: the centre of an opaque sphere from its saturated core.

For tungsten carbide, whose image below the clip is the far tail of the PSF shaped by streaks
rather than the sphere's edge (:mod:`.core_centroid`).  Away from an edge of the imaged region:
the mean of windowed centroids of the core at several margins, on the raw voxels around the
sub-voxel centroid.  Near an edge (where that patch is cut or holds padding): the default
centroid and its symmetric edge window with the core's ball and margin (:func:`core_edge_centre`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

from numpy.typing import NDArray

from registration.arrays import F64
from registration.detection.candidates import Support
from registration.detection.centroid import LINEAR_BACKGROUND_MIN_VOXELS, subvoxel_centre
from registration.detection.estimators.base import MeasuredSphere, SpherePatch, sphere_patch
from registration.detection.estimators.core_centroid import CoreWeights, core_centroid
from registration.detection.params import DetectionParams
from registration.detection.refine import edge_refined_centre


@dataclass(frozen=True, eq=False)
class CoreInput:
    """What ``core`` measures from: the sub-voxel centre (i, j, k); away from an edge the voxel
    patch and the core's weights, near one (``edge_centre_ijk`` set) the edge path's centre."""

    start_ijk: F64
    patch: SpherePatch | None = None
    weights: CoreWeights | None = None
    edge_centre_ijk: F64 | None = None


def core_edge_centre(
    vox: NDArray[Any],
    centre_ijk: F64,
    spacing: F64,
    params: DetectionParams,
    fov_radius_mm: float | None,
    support: Support | None = None,
) -> F64:
    """The ``core`` method's centre of a sphere near an edge of the imaged region: the default
    centroid and its symmetric edge window
    (:func:`~registration.detection.refine.edge_refined_centre`) with the core's ball and margin
    (``params.core``; on the tungsten-carbide hard-sweep scans better than the default ball and
    margin near an edge)."""
    cp = replace(params, bloom_mm=params.core.bloom_mm, centroid_margin_fraction=params.core.margin_fraction)
    c, _, _ = subvoxel_centre(vox, centre_ijk, spacing, cp, support)
    c, _ = edge_refined_centre(vox, c, spacing, cp, fov_radius_mm, support)
    return c


class CoreEstimator:
    """``prepare``: near an edge the edge path's centre, else the voxel patch and the core's
    weights; ``estimate``: that centre, or the core centroid (the sub-voxel one if it has none)."""

    circles_are_the_measurement = False

    def prepare(self, sphere: MeasuredSphere) -> CoreInput:
        p = sphere.params
        if sphere.near_edge():
            edge = core_edge_centre(
                sphere.vox, sphere.centre_ijk, sphere.spacing, p, sphere.fov_radius_mm, sphere.support
            )
            return CoreInput(sphere.centre_ijk, edge_centre_ijk=edge)
        weights = CoreWeights(
            p.core,
            margin_hu=p.centroid_margin_hu,
            shell_mm=p.background_shell_mm,
            min_shell_voxels=LINEAR_BACKGROUND_MIN_VOXELS,
        )
        return CoreInput(
            sphere.centre_ijk, sphere_patch(sphere.vox, sphere.centre_ijk, sphere.spacing, p), weights
        )

    def estimate(self, prepared: CoreInput) -> tuple[F64 | None, str]:
        if prepared.edge_centre_ijk is not None:
            return prepared.edge_centre_ijk, ""
        patch, weights = prepared.patch, prepared.weights
        if patch is None or weights is None:
            return prepared.start_ijk, ""
        c = core_centroid(
            patch.values_hu,
            patch.coords_mm,
            prepared.start_ijk * patch.spacing_mm,
            patch.radius_mm,
            patch.saturation_hu,
            weights,
        )
        return (prepared.start_ijk, "") if c is None else (c / patch.spacing_mm, "")


ESTIMATOR = CoreEstimator()
