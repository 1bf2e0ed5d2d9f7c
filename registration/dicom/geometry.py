"""Geometry rules for one series: check, sort along the slice normal, build ``image_from_voxel``.

Geometry (DICOM PS3.3 C.7.6.2.1.1): ImagePositionPatient (0020,0032) is the
centre of the first transmitted pixel; the first three values of
ImageOrientationPatient (0020,0037) are the direction cosines of a *row*
(direction of increasing column index i), the last three of a *column*
(increasing row index j); PixelSpacing (0028,0030) is (row spacing = distance
between rows, along j; column spacing = distance between columns, along i).

Each refusal is one small function (``check_*``) raising one error class of
:mod:`registration.dicom.errors`; :func:`check_series_geometry` runs them in order.
Slices are sorted by ``s = IPP · (row × col)``, never by SliceThickness (0018,0050),
InstanceNumber (0020,0013) or file order.
"""

from __future__ import annotations

import math
import statistics
from collections import defaultdict
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Final

import numpy as np

from registration.arrays import F64
from registration.dicom.errors import (
    MAX_FILES_IN_MESSAGE,
    DuplicatePositionError,
    GantryTiltError,
    IncompleteSeriesError,
    InconsistentImageSizeError,
    InvalidRescaleError,
    MissingGeometryError,
    MissingSliceError,
    MixedFrameOfReferenceError,
    MixedOrientationError,
    SeriesError,
    SingleSliceError,
    UnevenSpacingError,
    VolumeTooLargeError,
    file_names,
)
from registration.dicom.headers import SliceHeader, slice_name

ORIENTATION_TOLERANCE: Final = 1e-4
"""Max difference of any ImageOrientationPatient direction cosine between slices of one series
(dimensionless).  1e-4 rad tilts a plane by 0.0057°, i.e. 0.01 mm at 100 mm from the origin; slices of
one acquisition carry byte-identical values in practice, so anything above is a different orientation."""

ORTHONORMAL_TOLERANCE: Final = 1e-3
"""Max | |row| − 1 |, | |col| − 1 | and |row · col| accepted for ImageOrientationPatient.  Writers that
round cosines to 4–6 decimals stay well below; a hand-edited or corrupt header does not."""

PIXEL_SPACING_TOLERANCE_MM: Final = 5e-5
"""Max PixelSpacing difference between slices (mm).  A difference d moves the far edge of a 512-pixel
row by 512·d: 5e-5 mm keeps that under 0.026 mm, half the 0.05 mm localisation budget."""

SPACING_TOLERANCE_FRACTION: Final = 0.01
"""Max deviation of any slice step (and of any slice position from the uniform grid) from the nominal
spacing, as a fraction of it.  1 % of 0.833 mm = 0.008 mm, a sixth of the 0.05 mm localisation budget;
dicom2nifti and ITK likewise refuse (not resample) non-uniform stacks by default (image-side.md §1.2)."""

SPACING_TOLERANCE_MIN_MM: Final = 0.01
"""Floor of the spacing tolerance (mm): positions written as DS with 2 decimals are rounded by up to
0.005 mm, so one step can be off by 0.01 mm without anything being wrong.  Also the duplicate-position
threshold: two slices closer than this along the normal are the same slice."""

SHEAR_TOLERANCE_MM: Final = 0.02
"""Max sideways offset (mm) of any slice origin from the line through the first origin along the slice
normal.  5 % of a 0.415 mm pixel, 4x the 0.005 mm DS rounding; a 1° gantry tilt already gives
0.015 mm per 0.833 mm step and 2.8 mm over 192 slices."""

MAX_VOLUME_BYTES: Final = 4 * 1024**3
"""Largest volume the loader allocates (bytes, counted at 4 bytes per voxel since the output may become
float32).  4 GiB is a 1024³ float32 volume, 20x the commonly quoted 512 x 512 x 192 O-arm volume
(image-side.md §1.1) as float32.  Encapsulated PixelData is not size-checked before decoding, so a damaged
header's Rows / Columns would otherwise ask for tens of GiB before the decoder notices."""

AXIAL_MIN_NORMAL_Z: Final = math.cos(math.radians(45.0))
"""A stack counts as axial when |n_z| of its slice normal is at least cos 45°; axial stacks are
preferred when no series UID is given ("the largest consistent axial stack")."""


@dataclass(frozen=True, eq=False)
class SeriesGeometry:
    """A checked, sorted series: slices in increasing position along the normal, and its affine.

    Attributes
    ----------
    slices : tuple of SliceHeader
        Sorted by ``s = IPP · n`` ascending.
    image_from_voxel : ndarray, shape (4, 4), float64
        ``(i, j, k, 1)`` → LPS mm (see :func:`check_series_geometry`).
    positions_mm : ndarray, shape (n,), float64
        ``s`` of every sorted slice (mm along the normal).
    slice_spacing_mm : float
        ``(s_last − s_first) / (n − 1)``.
    """

    slices: tuple[SliceHeader, ...]
    image_from_voxel: F64
    positions_mm: F64
    slice_spacing_mm: float
    normal: F64 = field(repr=False)
    """(3,) float64: unit slice normal ``row × col`` in LPS."""


@dataclass(frozen=True, eq=False)
class SortedStack:
    """Slices sorted along the unit normal ``row_cos × col_cos`` (rules 6–9 work on this).

    ``ipp_mm`` (n, 3) float64 LPS mm and ``s_mm`` (n,) float64 mm are in sorted order;
    ``steps_mm`` (n − 1,) are the differences of ``s_mm``.
    """

    slices: tuple[SliceHeader, ...]
    ipp_mm: F64
    s_mm: F64
    steps_mm: F64
    row_cos: F64
    col_cos: F64
    normal: F64


def check_series_geometry(slices: Sequence[SliceHeader], series_uid: str = "") -> SeriesGeometry:
    """Check one series' slices, sort them along the slice normal and build ``image_from_voxel``.

    Rules, in the order they are checked (each raises the named error, naming the files):

    1. every slice has ImagePositionPatient (0020,0032), ImageOrientationPatient
       (0020,0037) with unit, orthogonal cosines, and PixelSpacing (0028,0030)
       → :class:`MissingGeometryError` (:func:`check_required_geometry`);
    2. at least two slices → :class:`SingleSliceError` (:func:`check_slice_count`);
    3. one FrameOfReferenceUID (0020,0052) → :class:`MixedFrameOfReferenceError`
       (:func:`check_frame_of_reference`);
    4. the same Rows (0028,0010), Columns (0028,0011) and PixelSpacing within
       :data:`PIXEL_SPACING_TOLERANCE_MM` → :class:`InconsistentImageSizeError`
       (:func:`check_image_size`, :func:`check_pixel_spacing`);
    5. the same orientation within :data:`ORIENTATION_TOLERANCE` → :class:`MixedOrientationError`
       (:func:`check_orientation`);
    6. no two slices within :data:`SPACING_TOLERANCE_MIN_MM` along the normal
       → :class:`DuplicatePositionError` (:func:`check_no_duplicates`);
    7. every origin within :data:`SHEAR_TOLERANCE_MM` of the line through the
       first origin along the normal → :class:`GantryTiltError` (:func:`check_no_shear`);
    8. no step a whole multiple (≥ 2) of the nominal (median) step → :class:`MissingSliceError`
       (:func:`check_no_missing_slices`);
    9. every step, and every position against the uniform grid, within
       ``max(SPACING_TOLERANCE_FRACTION · spacing, SPACING_TOLERANCE_MIN_MM)``
       → :class:`UnevenSpacingError` (:func:`check_even_steps`, :func:`check_uniform_grid`);
    10. as many slices as ImagesInAcquisition (0020,1002) announces, when a slice carries it
        → :class:`IncompleteSeriesError` (:func:`check_announced_count`).

    Between rules 4 and 5: the whole volume within :data:`MAX_VOLUME_BYTES`
    → :class:`VolumeTooLargeError` (:func:`check_volume_size`), and every slice's
    RescaleSlope (0028,1053) finite and non-zero, RescaleIntercept (0028,1052) finite
    → :class:`InvalidRescaleError` (:func:`check_rescale`).

    Slices are sorted by ``s = IPP · n`` with ``n = row × col`` (the row and
    column direction cosines of (0020,0037)).  The affine maps the index
    vector ``(i, j, k, 1)`` (column, row, slice) to LPS mm::

        column 0 = row cosine    · PixelSpacing[1]   (step along i, between columns)
        column 1 = column cosine · PixelSpacing[0]   (step along j, between rows)
        column 2 = (IPP_last − IPP_first) / (n − 1)  (mean sorted IPP step, along k)
        column 3 = IPP_first                         (centre of voxel (0, 0, 0))

    Since k follows increasing ``s``, ``det(image_from_voxel[:3, :3]) > 0``.
    """
    check_required_geometry(slices, series_uid)
    check_slice_count(slices, series_uid)
    check_frame_of_reference(slices, series_uid)
    check_image_size(slices, series_uid)
    check_pixel_spacing(slices, series_uid)
    check_volume_size(slices, series_uid)
    check_rescale(slices, series_uid)
    check_orientation(slices, series_uid)
    stack = sort_along_normal(slices)
    check_no_duplicates(stack, series_uid)
    check_no_shear(stack, series_uid)
    nominal_mm = float(statistics.median(stack.steps_mm.tolist()))
    tol_mm = spacing_tolerance_mm(nominal_mm)
    check_no_missing_slices(stack, nominal_mm, tol_mm, series_uid)
    check_even_steps(stack, nominal_mm, tol_mm, series_uid)
    spacing_mm = check_uniform_grid(stack, tol_mm, series_uid)
    check_announced_count(stack, series_uid)
    return SeriesGeometry(
        slices=stack.slices,
        image_from_voxel=image_from_voxel(stack, slices[0].pixel_spacing_mm or (0.0, 0.0)),
        positions_mm=stack.s_mm,
        slice_spacing_mm=spacing_mm,
        normal=stack.normal,
    )


def spacing_tolerance_mm(nominal_mm: float) -> float:
    """``max(SPACING_TOLERANCE_FRACTION · nominal, SPACING_TOLERANCE_MIN_MM)`` (rules 8 and 9)."""
    return max(SPACING_TOLERANCE_FRACTION * nominal_mm, SPACING_TOLERANCE_MIN_MM)


def is_axial(orientation: Sequence[float] | None) -> bool:
    """Slice normal within 45° of the patient z axis (:data:`AXIAL_MIN_NORMAL_Z`)."""
    if orientation is None:
        return False
    iop = np.asarray(orientation, dtype=np.float64)
    n = np.cross(iop[:3], iop[3:])
    norm = float(np.linalg.norm(n))
    return norm > 0 and abs(float(n[2])) / norm >= AXIAL_MIN_NORMAL_Z


# --------------------------------------------------------------------------- rules 1–5: per-slice values


def _orientation_problem(orientation: tuple[float, ...]) -> str:
    """``""`` when (0020,0037) is two orthogonal unit vectors within :data:`ORTHONORMAL_TOLERANCE`."""
    iop = np.asarray(orientation, dtype=np.float64)
    norms = np.linalg.norm(iop.reshape(2, 3), axis=1)
    unit_err = float(np.max(np.abs(norms - 1.0)))
    if unit_err > ORTHONORMAL_TOLERANCE or abs(float(iop[:3] @ iop[3:])) > ORTHONORMAL_TOLERANCE:
        return f"ImageOrientationPatient (0020,0037) {list(orientation)} is not two orthogonal unit vectors"
    return ""


def check_required_geometry(slices: Sequence[SliceHeader], series_uid: str) -> None:
    """Rule 1: position, unit orthogonal orientation, positive pixel spacing, one sample per pixel."""
    problems: dict[str, list[Path]] = defaultdict(list)
    for h in slices:
        if h.position_mm is None:
            problems["no valid ImagePositionPatient (0020,0032)"].append(h.path)
        if h.pixel_spacing_mm is None or min(h.pixel_spacing_mm) <= 0:
            problems["no valid PixelSpacing (0028,0030)"].append(h.path)
        if h.orientation is None:
            problems["no valid ImageOrientationPatient (0020,0037)"].append(h.path)
        elif what := _orientation_problem(h.orientation):
            problems[what].append(h.path)
        if h.samples_per_pixel != 1:
            problems[f"SamplesPerPixel {h.samples_per_pixel} (a CT slice has 1)"].append(h.path)
    if problems:
        described = "; ".join(f"{what}: {file_names(paths)}" for what, paths in problems.items())
        raise MissingGeometryError(
            f"series {series_uid}: slices without usable geometry: {described}. Without position, "
            "orientation and pixel spacing the voxels cannot be placed in patient space; re-export the "
            "series from the scanner.",
            files=[p for paths in problems.values() for p in paths],
            series_uid=series_uid,
        )


def check_slice_count(slices: Sequence[SliceHeader], series_uid: str) -> None:
    """Rule 2: at least two slices (one slice has no slice spacing)."""
    if len(slices) < 2:
        files = [h.path for h in slices]
        raise SingleSliceError(
            f"series {series_uid}: only {len(slices)} slice ({file_names(files)}); a volume needs at least 2 "
            "slices to know the slice spacing. Export the whole 3D series, not a single image.",
            files=files,
            series_uid=series_uid,
        )


def _check_same(
    slices: Sequence[SliceHeader],
    key: Callable[[SliceHeader], Hashable],
    error: type[SeriesError],
    what: str,
    series_uid: str,
    todo: str,
) -> None:
    by_value: dict[Hashable, list[Path]] = defaultdict(list)
    for h in slices:
        by_value[key(h)].append(h.path)
    if len(by_value) <= 1:
        return
    ranked = sorted(by_value.items(), key=lambda kv: -len(kv[1]))
    described = "; ".join(f"{value!s}: {len(paths)} file(s) ({file_names(paths)})" for value, paths in ranked)
    minority = [p for _, paths in ranked[1:] for p in paths]
    raise error(
        f"series {series_uid}: slices disagree on {what}: expected one value, found {described}. {todo}.",
        files=minority,
        series_uid=series_uid,
    )


def _check_close(
    slices: Sequence[SliceHeader],
    key: Callable[[SliceHeader], F64],
    tol: float,
    error: type[SeriesError],
    what: str,
    unit: str,
    series_uid: str,
) -> None:
    ref = key(slices[0])
    off = [h for h in slices if float(np.max(np.abs(key(h) - ref))) > tol]
    if not off:
        return
    same = [h.path for h in slices if float(np.max(np.abs(key(h) - ref))) <= tol]
    values = sorted({tuple(np.round(key(h), 6).tolist()) for h in off})
    raise error(
        f"series {series_uid}: slices disagree on {what} (tolerance {tol:g}{unit and ' ' + unit}): "
        f"{len(same)} file(s) have {tuple(np.round(ref, 6).tolist())} ({file_names(same)}), {len(off)} have "
        f"{', '.join(str(v) for v in values[:MAX_FILES_IN_MESSAGE])} ({file_names([h.path for h in off])}). "
        "Expected one value for the whole stack: remove the stray files (a scout or a reformat?) or "
        "re-export the series.",
        files=[h.path for h in off],
        series_uid=series_uid,
    )


def check_volume_size(slices: Sequence[SliceHeader], series_uid: str) -> None:
    """Refuse a stack whose voxels (at 4 bytes each) would exceed :data:`MAX_VOLUME_BYTES`."""
    h = slices[0]
    n_bytes = len(slices) * h.rows * h.columns * 4
    if n_bytes > MAX_VOLUME_BYTES:
        raise VolumeTooLargeError(
            f"series {series_uid}: {len(slices)} slices of {h.rows} x {h.columns} pixels would need "
            f"{n_bytes / 1024**3:.1f} GiB as float32, more than the loader's limit of "
            f"{MAX_VOLUME_BYTES / 1024**3:.1f} GiB (a 1024³ volume). Rows (0028,0010) / Columns (0028,0011) "
            f"of {slice_name(h)} are probably damaged; re-export the series.",
            files=[h.path],
            series_uid=series_uid,
        )


def check_rescale(slices: Sequence[SliceHeader], series_uid: str) -> None:
    """Refuse slices whose Modality LUT would turn every voxel into one value, NaN or infinity."""
    bad = [h for h in slices if h.slope == 0.0 or not (math.isfinite(h.slope) and math.isfinite(h.intercept))]
    if not bad:
        return
    values = sorted({f"({h.slope:g}, {h.intercept:g})" for h in bad})  # text: NaN != NaN in a set
    raise InvalidRescaleError(
        f"series {series_uid}: {len(bad)} slice(s) have an unusable rescale (RescaleSlope (0028,1053), "
        f"RescaleIntercept (0028,1052)) = {', '.join(values[:MAX_FILES_IN_MESSAGE])} "
        f"({file_names([h.path for h in bad])}); HU = slope · stored + intercept needs a finite, non-zero "
        "slope and a finite intercept. The headers are damaged; re-export the series.",
        files=[h.path for h in bad],
        series_uid=series_uid,
    )


def check_announced_count(stack: SortedStack, series_uid: str) -> None:
    """Rule 10: as many slices as ImagesInAcquisition (0020,1002) says, when any slice says it.

    A contiguous stack can still be the first half of an export that paused;
    only the count the scanner announces tells.  Several announced values: the largest counts.
    """
    announced = [h.expected_slices for h in stack.slices if h.expected_slices is not None]
    if not announced:
        return
    expected, found = max(announced), len(stack.slices)
    if found == expected:
        return
    more = "fewer" if found < expected else "more"
    raise IncompleteSeriesError(
        f"series {series_uid}: {found} slices found, {more} than the {expected} that ImagesInAcquisition "
        f"(0020,1002) announces (positions {stack.s_mm[0]:.2f}..{stack.s_mm[-1]:.2f} mm along the normal). "
        "The export is unfinished or mixed: wait for it to finish, or re-export the series.",
        files=[h.path for h in stack.slices[:1]],
        series_uid=series_uid,
    )


def check_frame_of_reference(slices: Sequence[SliceHeader], series_uid: str) -> None:
    """Rule 3: one FrameOfReferenceUID (0020,0052)."""
    _check_same(
        slices,
        lambda h: h.frame_of_reference_uid,
        MixedFrameOfReferenceError,
        "FrameOfReferenceUID (0020,0052)",
        series_uid,
        "the slices were not acquired in one coordinate system; re-export the series from the scanner "
        "(or pass the series UID of a clean series)",
    )


def check_image_size(slices: Sequence[SliceHeader], series_uid: str) -> None:
    """Rule 4a: the same Rows (0028,0010) and Columns (0028,0011)."""
    _check_same(
        slices,
        lambda h: (h.rows, h.columns),
        InconsistentImageSizeError,
        "Rows x Columns (0028,0010)/(0028,0011)",
        series_uid,
        "remove the files that do not belong to this stack, or re-export the series",
    )


def check_pixel_spacing(slices: Sequence[SliceHeader], series_uid: str) -> None:
    """Rule 4b: PixelSpacing (0028,0030) within :data:`PIXEL_SPACING_TOLERANCE_MM` of the first slice's."""
    _check_close(
        slices,
        lambda h: np.asarray(h.pixel_spacing_mm, dtype=np.float64),
        PIXEL_SPACING_TOLERANCE_MM,
        InconsistentImageSizeError,
        "PixelSpacing (0028,0030)",
        "mm",
        series_uid,
    )


def check_orientation(slices: Sequence[SliceHeader], series_uid: str) -> None:
    """Rule 5: ImageOrientationPatient (0020,0037) within :data:`ORIENTATION_TOLERANCE` of the first's."""
    _check_close(
        slices,
        lambda h: np.asarray(h.orientation, dtype=np.float64),
        ORIENTATION_TOLERANCE,
        MixedOrientationError,
        "ImageOrientationPatient (0020,0037)",
        "",
        series_uid,
    )


# --------------------------------------------------------------------------- rules 6–9: the sorted stack


def sort_along_normal(slices: Sequence[SliceHeader]) -> SortedStack:
    """Sort by ``s = IPP · n``, ``n`` the unit normal of the first slice's (0020,0037) (stable for ties)."""
    iop = np.asarray(slices[0].orientation, dtype=np.float64)
    row_cos = iop[:3] / np.linalg.norm(iop[:3])
    col_cos = iop[3:] / np.linalg.norm(iop[3:])
    normal = np.cross(row_cos, col_cos)
    normal /= np.linalg.norm(normal)
    ipp = np.array([h.position_mm for h in slices], dtype=np.float64)
    s_unsorted = ipp @ normal
    order = np.argsort(s_unsorted, kind="stable")
    s = s_unsorted[order]
    return SortedStack(
        slices=tuple(slices[int(m)] for m in order),
        ipp_mm=ipp[order],
        s_mm=s,
        steps_mm=np.diff(s),
        row_cos=row_cos,
        col_cos=col_cos,
        normal=normal,
    )


def check_no_duplicates(stack: SortedStack, series_uid: str) -> None:
    """Rule 6: no two slices closer than :data:`SPACING_TOLERANCE_MIN_MM` along the normal."""
    dup = np.flatnonzero(stack.steps_mm < SPACING_TOLERANCE_MIN_MM)
    if not dup.size:
        return
    ordered, s = stack.slices, stack.s_mm
    pairs = [(ordered[m], ordered[m + 1]) for m in dup]
    same_uid = [a for a, b in pairs if a.sop_instance_uid == b.sop_instance_uid]
    described = "; ".join(
        f"{slice_name(a)} and {slice_name(b)} at s = {s[m]:.3f} mm"
        for (a, b), m in zip(pairs, dup, strict=True)
    )
    hint = (
        " (same SOPInstanceUID: a copied file; delete the copy)"
        if same_uid
        else " (two acquisitions or reconstructions mixed into one series?)"
    )
    raise DuplicatePositionError(
        f"series {series_uid}: {dup.size} pair(s) of slices share a position along the slice normal "
        f"(closer than {SPACING_TOLERANCE_MIN_MM} mm): {described}{hint}. Expected one slice per "
        "position; remove the duplicates or re-export the series.",
        files=[p.path for pair in pairs for p in pair],
        series_uid=series_uid,
    )


def check_no_shear(stack: SortedStack, series_uid: str) -> None:
    """Rule 7: every origin within :data:`SHEAR_TOLERANCE_MM` of the line through the first, along n."""
    d = stack.ipp_mm - stack.ipp_mm[0]
    sideways = d - np.outer(d @ stack.normal, stack.normal)
    offset_mm = np.linalg.norm(sideways, axis=1)
    worst = int(np.argmax(offset_mm))
    if offset_mm[worst] <= SHEAR_TOLERANCE_MM:
        return
    ordered = stack.slices
    along = float(stack.s_mm[worst] - stack.s_mm[0])
    tilt_deg = math.degrees(math.atan2(float(offset_mm[worst]), abs(along))) if along else 90.0
    raise GantryTiltError(
        f"series {series_uid}: slice origins are not on one line along the slice normal: "
        f"{slice_name(ordered[worst])} is {offset_mm[worst]:.3f} mm sideways of the line through "
        f"{slice_name(ordered[0])} (tolerance {SHEAR_TOLERANCE_MM} mm; "
        f"a gantry tilt of about {tilt_deg:.2f}° or a shifted slice). A sheared stack cannot be loaded "
        "as a rectangular volume: re-scan or re-export without gantry tilt.",
        files=[ordered[0].path, ordered[worst].path],
        series_uid=series_uid,
    )


def check_no_missing_slices(stack: SortedStack, nominal_mm: float, tol_mm: float, series_uid: str) -> None:
    """Rule 8: no step a whole multiple (≥ 2) of the nominal step, within ``tol_mm`` per multiple."""
    steps, s, ordered = stack.steps_mm, stack.s_mm, stack.slices
    multiples = np.rint(steps / nominal_mm)
    gaps = np.flatnonzero((multiples >= 2) & (np.abs(steps - multiples * nominal_mm) <= tol_mm * multiples))
    if not gaps.size:
        return
    described = "; ".join(
        f"{int(multiples[m]) - 1} missing between {slice_name(ordered[m])} (s = {s[m]:.3f} mm) and "
        f"{slice_name(ordered[m + 1])} (s = {s[m + 1]:.3f} mm)"
        for m in gaps[:MAX_FILES_IN_MESSAGE]
    )
    more = f" (+{gaps.size - MAX_FILES_IN_MESSAGE} more gaps)" if gaps.size > MAX_FILES_IN_MESSAGE else ""
    raise MissingSliceError(
        f"series {series_uid}: slices are missing (spacing {nominal_mm:.4f} mm): {described}{more}. "
        "The export is incomplete: wait for the transfer to finish or re-export the series.",
        files=[p for m in gaps for p in (ordered[m].path, ordered[m + 1].path)],
        series_uid=series_uid,
    )


def check_even_steps(stack: SortedStack, nominal_mm: float, tol_mm: float, series_uid: str) -> None:
    """Rule 9a: every step within ``tol_mm`` of the nominal (median) step."""
    steps, ordered = stack.steps_mm, stack.slices
    bad = np.flatnonzero(np.abs(steps - nominal_mm) > tol_mm)
    if not bad.size:
        return
    described = "; ".join(
        f"{slice_name(ordered[m])} → {slice_name(ordered[m + 1])}: {steps[m]:.4f} mm"
        for m in bad[:MAX_FILES_IN_MESSAGE]
    )
    more = f" (+{bad.size - MAX_FILES_IN_MESSAGE} more)" if bad.size > MAX_FILES_IN_MESSAGE else ""
    raise UnevenSpacingError(
        f"series {series_uid}: uneven slice spacing: expected every step to be {nominal_mm:.4f} mm "
        f"± {tol_mm:.4f} mm, found {described}{more}. A non-uniform stack is not resampled; re-export "
        "the series with uniform spacing.",
        files=[p for m in bad for p in (ordered[m].path, ordered[m + 1].path)],
        series_uid=series_uid,
    )


def check_uniform_grid(stack: SortedStack, tol_mm: float, series_uid: str) -> float:
    """Rule 9b: every position within ``tol_mm`` of the uniform grid; returns its spacing (mm)."""
    s, n = stack.s_mm, len(stack.slices)
    spacing_mm = float(s[-1] - s[0]) / (n - 1)
    drift = np.abs(s - (s[0] + spacing_mm * np.arange(n)))
    worst = int(np.argmax(drift))
    if drift[worst] > tol_mm:
        raise UnevenSpacingError(
            f"series {series_uid}: uneven slice spacing: {slice_name(stack.slices[worst])} is "
            f"{drift[worst]:.4f} mm off the uniform grid of {spacing_mm:.4f} mm (tolerance {tol_mm:.4f} mm). "
            "Re-export the series with uniform spacing.",
            files=[stack.slices[worst].path],
            series_uid=series_uid,
        )
    return spacing_mm


def image_from_voxel(stack: SortedStack, pixel_spacing_mm: Sequence[float]) -> F64:
    """The (4, 4) float64 affine ``(i, j, k, 1)`` → LPS mm of a checked stack (see the module rules)."""
    row_mm, col_mm = pixel_spacing_mm
    n = len(stack.slices)
    out = np.eye(4, dtype=np.float64)
    out[:3, 0] = stack.row_cos * col_mm  # i: along a row, spacing between columns = PixelSpacing[1]
    out[:3, 1] = stack.col_cos * row_mm  # j: down a column, spacing between rows = PixelSpacing[0]
    out[:3, 2] = (stack.ipp_mm[-1] - stack.ipp_mm[0]) / (n - 1)
    out[:3, 3] = stack.ipp_mm[0]
    return out
