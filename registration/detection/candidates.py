"""Step 1 of the detection: bright blobs that may be spheres, from one pass over the volume.

One vectorised threshold of the whole volume (``voxels >= candidate_threshold_hu``, slab by slab,
no float copy), the hits grouped through a coarse cell grid, each group's crop labelled
(26-connectivity) and every component measured (extent, volume, peak).  Only small crops are
ever copied.  A blob too large or too sparse for one sphere (streak tails joining it to its
neighbours, spheres joined by blooms) is split into sphere cores by a morphological opening
(:func:`split_blob`).  What is kept or rejected is decided by :mod:`.rejections`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Final

import cc3d
import numpy as np
from numpy.typing import NDArray

from registration.arrays import F64
from registration.detection.params import DetectionParams

Support = tuple[tuple[slice, slice, slice], NDArray[np.bool_]]
"""A region of the volume: a (k, j, i) box and a boolean mask of the box's shape."""


def threshold_hits(vox: NDArray[Any], threshold_hu: float) -> tuple[NDArray[np.intp], float]:
    """Flat indices of voxels ≥ the threshold (one pass, no float copy) and the threshold as compared.

    For an integer volume the threshold is rounded up to the stored type; one above its maximum
    gives no hits.
    """
    integer = np.issubdtype(vox.dtype, np.integer)
    thr_cast = float(np.ceil(threshold_hu)) if integer else float(threshold_hu)
    if integer and thr_cast > np.iinfo(vox.dtype).max:
        return np.zeros(0, dtype=np.intp), thr_cast
    thr = np.asarray(thr_cast).astype(vox.dtype)
    # Slab by slab into one small reused mask: a whole-volume mask (50 MB for 512² × 192) costs
    # more in first-touch page faults than the comparison itself (benchmarks/bench_detect_process.py).
    per_slice = int(np.prod(vox.shape[1:]))
    n_slab = max(1, THRESHOLD_SLAB_VOXELS // max(per_slice, 1))
    mask = np.empty((min(n_slab, vox.shape[0]), *vox.shape[1:]), dtype=bool)
    hits: list[NDArray[np.intp]] = []
    for k0 in range(0, vox.shape[0], n_slab):
        slab = vox[k0 : k0 + n_slab]
        m = mask[: slab.shape[0]]
        np.greater_equal(slab, thr, out=m)
        hits.append(np.flatnonzero(m) + k0 * per_slice)
    return (np.concatenate(hits) if hits else np.zeros(0, dtype=np.intp)), thr_cast


THRESHOLD_SLAB_VOXELS: Final = 1 << 21
"""Voxels per slab of :func:`threshold_hits` (8 slices of 512²: a 2 MB mask, cache-sized)."""


_GROUP_CELL_VOXELS: Final = (4, 8, 8)
"""(k, j, i) size of the coarse cells used to group threshold hits: ~3.3 mm, far below the 15 mm pitch."""


def group_hits(flat: NDArray[np.intp], shape: tuple[int, int, int]) -> list[tuple[slice, slice, slice]]:
    """Bounding boxes (k, j, i slices) of clusters of threshold hits, via a coarse cell grid."""
    k, j, i = np.unravel_index(flat, shape)
    ck, cj, ci = _GROUP_CELL_VOXELS
    grid_shape = (shape[0] // ck + 1, shape[1] // cj + 1, shape[2] // ci + 1)
    cell = (k // ck, j // cj, i // ci)
    occ = np.zeros(grid_shape, dtype=bool)
    occ[cell] = True
    labels, n = cc3d.connected_components(occ, connectivity=26, return_N=True)
    hit_label = labels[cell]
    boxes: list[tuple[slice, slice, slice]] = []
    order = np.argsort(hit_label, kind="stable")
    bounds = np.searchsorted(hit_label[order], np.arange(1, n + 2))
    for g in range(n):
        idx = order[bounds[g] : bounds[g + 1]]
        if len(idx) == 0:
            continue
        boxes.append(
            (
                slice(int(k[idx].min()), int(k[idx].max()) + 1),
                slice(int(j[idx].min()), int(j[idx].max()) + 1),
                slice(int(i[idx].min()), int(i[idx].max()) + 1),
            )
        )
    return boxes


def _expand(
    box: tuple[slice, slice, slice], margin: tuple[int, int, int], shape: tuple[int, int, int]
) -> tuple[slice, slice, slice]:
    return (
        slice(max(box[0].start - margin[0], 0), min(box[0].stop + margin[0], shape[0])),
        slice(max(box[1].start - margin[1], 0), min(box[1].stop + margin[1], shape[1])),
        slice(max(box[2].start - margin[2], 0), min(box[2].stop + margin[2], shape[2])),
    )


@dataclass
class Blob:
    """A connected above-threshold component (internal)."""

    box: tuple[slice, slice, slice]  # in the full volume, (k, j, i)
    n_voxels: int
    peak_hu: float
    centroid_voxel: F64  # (i, j, k)
    extent_mm: F64  # (3,) along i, j, k
    support: Support | None = None
    """A split core's region (box in the volume, mask in it): outside it, slice patches are
    flattened to the circle window's floor so the streak tails cut off by the split do not
    distort the cross-sections.  None for an unsplit blob."""


def find_blobs(
    vox: NDArray[Any],
    boxes: list[tuple[slice, slice, slice]],
    threshold_hu: float,
    spacing: F64,
    crop_margin_mm: float,
) -> list[Blob]:
    """Connected (26-neighbour) above-threshold components inside each group's crop, measured and
    sorted by (k, j, i) of their bounding box."""
    shape = (vox.shape[0], vox.shape[1], vox.shape[2])
    margin = tuple(math.ceil(crop_margin_mm / s) + 1 for s in (spacing[2], spacing[1], spacing[0]))
    blobs: list[Blob] = []
    for box in boxes:
        crop_box = _expand(box, (margin[0], margin[1], margin[2]), shape)
        crop = vox[crop_box]
        labels, boxes_in_crop = components_26(crop >= threshold_hu)
        for lab, sl in enumerate(boxes_in_crop, start=1):
            blobs.append(_measure_component(crop, labels[sl] == lab, sl, crop_box, spacing))
    blobs.sort(key=lambda b: (b.box[0].start, b.box[1].start, b.box[2].start))
    return blobs


def components_26(mask: NDArray[np.bool_]) -> tuple[NDArray[Any], list[tuple[slice, ...]]]:
    """26-connected components of a 3-D mask: labels 1 … n (0 outside) and each one's (k, j, i) box.

    :func:`cc3d.connected_components` numbers them in raster order, as ``scipy.ndimage.label``
    with a 3 × 3 × 3 structure does (and the boxes equal ``scipy.ndimage.find_objects``), without
    scipy.ndimage's import (0.3–1 s, more than the detection of a 512² × 192 scan; measured by
    benchmarks/bench_detect_process.py).
    """
    labels, n = cc3d.connected_components(mask, connectivity=26, return_N=True)
    return labels, (list(cc3d.statistics(labels)["bounding_boxes"][1 : n + 1]) if n else [])


def _measure_component(
    crop: NDArray[Any],
    sub: NDArray[np.bool_],
    sl: tuple[slice, ...],
    crop_box: tuple[slice, slice, slice],
    spacing: F64,
) -> Blob:
    kk, jj, ii = np.nonzero(sub)
    off = (
        crop_box[0].start + sl[0].start,
        crop_box[1].start + sl[1].start,
        crop_box[2].start + sl[2].start,
    )
    full_box = (
        slice(off[0], off[0] + sub.shape[0]),
        slice(off[1], off[1] + sub.shape[1]),
        slice(off[2], off[2] + sub.shape[2]),
    )
    return Blob(
        box=full_box,
        n_voxels=int(sub.sum()),
        peak_hu=float(crop[sl][sub].max()),
        centroid_voxel=np.array([ii.mean() + off[2], jj.mean() + off[1], kk.mean() + off[0]]),
        extent_mm=np.array(sub.shape[::-1], dtype=np.float64) * spacing,
    )


def _ellipsoid(semi_axes_vox: tuple[float, float, float]) -> NDArray[np.bool_]:
    """Boolean (k, j, i) ellipsoid with the given semi-axes in voxels (at least the centre voxel)."""
    half = [math.floor(a) for a in semi_axes_vox]
    kk, jj, ii = np.ogrid[-half[0] : half[0] + 1, -half[1] : half[1] + 1, -half[2] : half[2] + 1]
    a = [max(x, 1e-9) for x in semi_axes_vox]
    return np.asarray((kk / a[0]) ** 2 + (jj / a[1]) ** 2 + (ii / a[2]) ** 2 <= 1.0)


SUPPORT_GROW_VOXELS: Final = 1.0
"""A split core's support is its opened mask dilated by this many voxels: the opening shaved the
bloom edge by up to a voxel, and the circle finder needs the 2000 → 500 HU edge ramp (≈ 1 voxel at
0.4 mm pixels with a 0.8 mm PSF) around it."""


def split_blob(
    vox: NDArray[Any],
    b: Blob,
    threshold_hu: float,
    spacing: F64,
    params: DetectionParams,
    core_fraction: float | None = None,
) -> list[Blob]:
    """The sphere-core components of an oversized blob: its metal mask opened by an ellipsoid.

    The opening (radius ``core_fraction``, by default ``split_core_fraction``, × the nominal
    radius, per axis in voxels) removes
    streaks and bloom bridges narrower than that, so a sphere with streak tails, or spheres joined
    by them, fall apart into cores; a rod stays one elongated component.  Returns the cores as
    blobs (measured on the opened mask, peak from the raw voxels), in (k, j, i) order.
    """
    from scipy import ndimage  # here only: an oversized blob is rare, the import costs 0.3–1 s

    shape = (vox.shape[0], vox.shape[1], vox.shape[2])
    rho_mm = (params.split_core_fraction if core_fraction is None else core_fraction) * params.radius_mm
    semi = (rho_mm / float(spacing[2]), rho_mm / float(spacing[1]), rho_mm / float(spacing[0]))
    pad = tuple(math.floor(a) + 1 for a in semi)
    crop_box = _expand(b.box, (pad[0], pad[1], pad[2]), shape)
    crop = vox[crop_box]
    opened = ndimage.binary_opening(crop >= threshold_hu, structure=_ellipsoid(semi))
    labels, _ = ndimage.label(opened, structure=np.ones((3, 3, 3), dtype=bool))
    grow = _ellipsoid((SUPPORT_GROW_VOXELS, SUPPORT_GROW_VOXELS, SUPPORT_GROW_VOXELS))
    cores = []
    for lab, sl in enumerate(ndimage.find_objects(labels), start=1):
        if sl is None:
            continue
        core = _measure_component(crop, labels[sl] == lab, sl, crop_box, spacing)
        core.support = (crop_box, ndimage.binary_dilation(labels == lab, structure=grow))
        cores.append(core)
    cores.sort(key=lambda c: (c.box[0].start, c.box[1].start, c.box[2].start))
    return cores
