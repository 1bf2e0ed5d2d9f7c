"""Load one CT series from a folder or a DICOMDIR file-set into a
:class:`~registration.imaging.volume.Volume`.

The loader is the one I/O edge of :mod:`registration` (design.md §3,
research/image-side.md §1.2): find files and read their headers
(:mod:`~registration.dicom.selection`, :mod:`~registration.dicom.headers`), pick
the series, check and sort its slices (:mod:`~registration.dicom.geometry`), then
decode the pixels once into one preallocated array (:mod:`~registration.dicom.pixels`).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from registration.dicom.geometry import SeriesGeometry
from registration.dicom.headers import SkippedFile
from registration.dicom.pixels import read_voxels
from registration.dicom.selection import (
    FolderScan,
    SeriesSummary,
    group_by_series,
    scan_folder,
    select_series,
    summarise,
)
from registration.imaging.volume import Volume

log = logging.getLogger(__name__)


def load_series(path: str | Path, *, series_uid: str | None = None, unique: bool = False) -> Volume:
    """Load one CT series as a :class:`Volume` in Hounsfield units.

    Parameters
    ----------
    path : str or Path
        A folder (searched recursively), a ``DICOMDIR`` file, a folder with a
        ``DICOMDIR`` at its root (read as a File-set), or a single file.
    series_uid : str, optional
        SeriesInstanceUID (0020,000E) to load.  Without it the largest
        consistent stack is taken (axial stacks first); a tie is refused.
    unique : bool
        Refuse (:class:`AmbiguousSeriesError`) when more than one series is loadable and
        ``series_uid`` names none: the command line, where a folder of several scans must not
        silently give the largest one.  Hidden folders, virtual environments and
        package trees under ``path`` are never searched.

    Returns
    -------
    Volume
        ``voxels`` shape (n_slices, rows, columns), indexed ``[k, j, i]``,
        int16 HU when every slice's rescale is integral and the values fit,
        else float32 HU.  ``image_from_voxel`` as in
        :func:`check_series_geometry`.  ``meta`` holds ``files`` (slice order),
        ``skipped`` ((path, reason) pairs), ``slice_spacing_mm``,
        ``positions_mm``, ``instance_numbers``, ``transfer_syntax_uids``,
        ``rescale`` ((slope, intercept) set), ``manufacturer``,
        ``acquisition``, ``study_uid``, ``series_description``.

    Raises
    ------
    SeriesError
        A subclass of :class:`~registration.errors.DicomSeriesError` saying what
        was wrong, naming the files, and what to do: :class:`NoCtSeriesError`,
        :class:`SeriesNotFoundError`, :class:`AmbiguousSeriesError`, the
        geometry refusals of :func:`check_series_geometry`, :class:`PixelDataError`.
    """
    root = Path(path)
    headers, skipped = scan_folder(root)
    groups = group_by_series(headers)
    chosen_uid, geometry = select_series(root, groups, skipped, series_uid, unique=unique)
    voxels = read_voxels(geometry.slices, chosen_uid)
    first = geometry.slices[0]
    meta = volume_meta(root, geometry, skipped)
    log.info(
        "loaded series %s: %d slices of %dx%d, spacing %.4f mm, %s, %d file(s) skipped",
        chosen_uid,
        voxels.shape[0],
        voxels.shape[1],
        voxels.shape[2],
        geometry.slice_spacing_mm,
        voxels.dtype,
        len(skipped),
    )
    return Volume(
        voxels=voxels,
        image_from_voxel=geometry.image_from_voxel,
        series_uid=chosen_uid,
        frame_of_reference_uid=first.frame_of_reference_uid,
        meta=meta,
    )


def list_series(path: str | Path) -> list[SeriesSummary]:
    """Header-only list of the CT series under ``path``, largest first.

    Cheap (pixel data are never read or decoded) so a folder watcher can call
    it on every change: a series is complete and loadable when
    ``summary.consistent`` and its ``n_files`` stopped changing.
    """
    return list(read_series_headers(path).series)


def read_series_headers(path: str | Path) -> FolderScan:
    """Header pass over ``path``: every CT series summarised, every skipped file with its reason."""
    root = Path(path)
    headers, skipped = scan_folder(root)
    groups = group_by_series(headers)
    summaries = [summarise(uid, hs) for uid, hs in groups.items()]
    summaries.sort(key=lambda s: (-s.n_slices, s.series_uid))
    return FolderScan(root=root, series=tuple(summaries), skipped=tuple(skipped))


def volume_meta(root: Path, geometry: SeriesGeometry, skipped: Sequence[SkippedFile]) -> dict[str, Any]:
    """:attr:`Volume.meta` of a loaded series (see :func:`load_series`)."""
    first = geometry.slices[0]
    return {
        "source": str(root),
        "files": tuple(str(h.path) for h in geometry.slices),
        "frames": tuple(h.frame for h in geometry.slices),
        "skipped": tuple((str(s.path), s.reason) for s in skipped),
        "slice_spacing_mm": geometry.slice_spacing_mm,
        "positions_mm": tuple(float(s) for s in geometry.positions_mm),
        "instance_numbers": tuple(h.instance_number for h in geometry.slices),
        "transfer_syntax_uids": tuple(sorted({h.transfer_syntax_uid for h in geometry.slices})),
        "rescale": tuple(sorted({(h.slope, h.intercept) for h in geometry.slices})),
        "sop_class_uid": first.sop_class_uid,
        "modality": first.modality,
        "manufacturer": first.manufacturer,
        "acquisition": first.acquisition,
        "study_uid": first.study_uid,
        "series_description": first.series_description,
    }
