"""Decode a C-STORE series slice by slice as it arrives, so the volume is ready at association release.

The DICOM Storage SCP (:mod:`service.intake.storage_scp`) writes each instance to disk and hands its path
here; worker threads read its header and pixel data with the same functions the series loader
uses (:mod:`registration.dicom`: the header pass :func:`~registration.dicom.headers.read_headers`,
the HU rescale :func:`~registration.dicom.pixels.read_voxels`) and copy its frames into one
growing (capacity, rows, columns) array, one row per frame in arrival order (each row is
written once: a replaced instance gets a new row).  At release :meth:`SeriesAccumulator.assemble`
waits for the last decodes, runs the loader's geometry checks
(:func:`~registration.dicom.check_series_geometry` — one Frame of Reference, one image size
and orientation, contiguous evenly spaced positions, the announced count) on every slice's
header and returns the volume in slice order: a read-only view of those rows when they arrived
in slice order (the usual case: no copy at release), else one gather.  Its ``meta`` is the
loader's plus ``decoded_on_arrival`` and ``sop_uids`` ((SOP Instance UID, SOP Class UID) of each
slice, in slice order: what an SRO references, without reading the files again).

Whenever the decoded set is not exactly the series folder's ``*.dcm`` files (a series reopened by
a later association, a file the header pass skipped, a decode that failed), it falls back to
:func:`~registration.dicom.load_series` on the folder, so the outcome is always the
loader's.
"""

from __future__ import annotations

import logging
import threading
import time
from concurrent.futures import Executor, Future
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from registration.imaging.volume import Volume

log = logging.getLogger(__name__)

INITIAL_CAPACITY_FRAMES = 64
"""Frames the array holds before its first growth (doubling) when the series does not announce
its count (ImagesInAcquisition); 64 × 512 × 512 int16 is 32 MB of address space, touched only
as frames arrive."""


@dataclass(frozen=True)
class _Decoded:
    headers: tuple[Any, ...]
    """:class:`registration.dicom.SliceHeader` of each frame of the file."""
    rows: tuple[int, ...] | None
    """Row of each frame in the accumulator's array; None when it could not be placed there (a
    different image size than the first file: the loader gives the named refusal)."""


class _Frames:
    """The decoded frames of one series in one array, grown by doubling (not thread-safe: the
    accumulator's lock guards it)."""

    def __init__(self) -> None:
        self.array: NDArray[Any] | None = None
        self.reserved = 0
        """Rows handed out so far (a row per expected frame, in arrival order)."""

    def reserve(self) -> int:
        self.reserved += 1
        return self.reserved - 1

    def place(self, row: int | None, planes: NDArray[Any], expected: int | None) -> tuple[int, ...] | None:
        """Copy ``planes`` (n, rows, columns) in at ``row`` (one plane) or at the end; their rows."""
        n, shape = len(planes), planes.shape[1:]
        if self.array is not None and self.array.shape[1:] != shape:
            return None
        rows = [row] if row is not None and n == 1 else [self.reserve() for _ in range(n)]
        self._fit(max(rows) + 1, shape, planes.dtype, expected)
        assert self.array is not None
        for r, plane in zip(rows, planes, strict=True):
            self.array[r] = plane
        return tuple(rows)

    def _fit(self, n_rows: int, shape: tuple[int, ...], dtype: Any, expected: int | None) -> None:
        arr = self.array
        want = np.result_type(dtype, arr.dtype) if arr is not None else np.dtype(dtype)
        cap = len(arr) if arr is not None else max(expected or 0, INITIAL_CAPACITY_FRAMES)
        while cap < max(n_rows, self.reserved):
            cap *= 2
        if arr is not None and cap == len(arr) and want == arr.dtype:
            return
        grown: NDArray[Any] = np.empty((cap, *shape), dtype=want)
        if arr is not None:
            grown[: len(arr)] = arr  # rows not written yet are copied as garbage and written later
        self.array = grown


class SeriesAccumulator:
    """The instances of one series folder received so far, decoded on ``executor``.

    Thread-safe: :meth:`add` runs on pynetdicom's association thread, the decodes on the
    executor's workers (any number), :meth:`assemble` on a service worker thread.
    """

    def __init__(self, series_dir: Path, executor: Executor) -> None:
        self.series_dir = series_dir
        self._executor = executor
        self._lock = threading.Lock()
        self._futures: dict[Path, Future[_Decoded | None]] = {}
        self._frames = _Frames()
        self.new_instances = 0
        """Instances stored or replaced (not identical re-sends)."""
        self.received = 0
        self.first_t_s = time.monotonic()
        self.first_at = datetime.now(UTC)
        self.last_t_s = self.first_t_s

    def add(self, path: Path, outcome: str) -> None:
        """One instance is on disk (``outcome`` as reported by the SCP)."""
        with self._lock:
            self.received += 1
            self.last_t_s = time.monotonic()
            if outcome != "duplicates":
                self.new_instances += 1
            if outcome == "duplicates" and path in self._futures:
                return
            row = self._frames.reserve()
            self._futures[path] = self._executor.submit(self._decode, path, row)

    def _decode(self, path: Path, row: int) -> _Decoded | None:
        """Header + HU pixels of one file into the array, or None when the loader would skip it."""
        from registration.dicom import SkippedFile
        from registration.dicom.headers import read_headers
        from registration.dicom.pixels import read_voxels

        result = read_headers(path)
        if isinstance(result, SkippedFile) or not result:
            return None
        voxels = read_voxels(result, result[0].series_uid)
        expected = max((h.expected_slices or 0 for h in result), default=0) or None
        with self._lock:
            rows = self._frames.place(row, voxels, expected)
        return _Decoded(tuple(result), rows)

    def assemble(self, series_uid: str) -> Volume:
        """The series' volume (checked as the loader checks it).

        Raises
        ------
        DicomSeriesError
            The loader's refusal (missing slice, mixed geometry, undecodable pixels...).
        OSError
            The folder cannot be read.
        """
        from registration.dicom import load_series

        with self._lock:
            futures = dict(self._futures)
        on_disk = {p for p in self.series_dir.glob("*.dcm")}
        decoded: dict[Path, _Decoded] = {}
        for path, fut in futures.items():
            try:
                d = fut.result()
            except Exception as e:  # the loader gives the named refusal
                log.info("series %s: decoding %s failed (%s); loading the folder", series_uid, path.name, e)
                return load_series(self.series_dir, series_uid=series_uid)
            if d is not None:
                decoded[path] = d
        if (
            set(decoded) != on_disk
            or any(d.rows is None for d in decoded.values())
            or any(h.series_uid != series_uid for d in decoded.values() for h in d.headers)
        ):
            return load_series(self.series_dir, series_uid=series_uid)
        with self._lock:
            array = self._frames.array
        assert array is not None  # at least one file decoded and placed
        return _stack(self.series_dir, series_uid, decoded, array)


def _stack(root: Path, series_uid: str, decoded: dict[Path, _Decoded], array: NDArray[Any]) -> Volume:
    """Check the geometry of every slice; the frames in slice order (a view when already in order)."""
    from registration.dicom import check_series_geometry
    from registration.dicom.loader import volume_meta  # the loader's own meta, key for key

    row_of: dict[tuple[Path, int], int] = {}
    headers = []
    for d in decoded.values():
        assert d.rows is not None
        for h, r in zip(d.headers, d.rows, strict=True):
            row_of[(h.path, h.frame)] = r
            headers.append(h)
    geometry = check_series_geometry(headers, series_uid)
    order = np.fromiter((row_of[(h.path, h.frame)] for h in geometry.slices), dtype=np.intp)
    first_row = int(order[0])
    if np.array_equal(order, np.arange(first_row, first_row + len(order))):
        voxels = array[first_row : first_row + len(order)]
    else:
        voxels = array[order]
    voxels.flags.writeable = False  # rows are written once; nothing downstream may change them
    first = geometry.slices[0]
    meta: dict[str, Any] = {
        **volume_meta(root, geometry, ()),
        "decoded_on_arrival": True,
        "sop_uids": tuple((h.sop_instance_uid, h.sop_class_uid) for h in geometry.slices),
    }
    return Volume(
        voxels=voxels,
        image_from_voxel=geometry.image_from_voxel,
        series_uid=series_uid,
        frame_of_reference_uid=first.frame_of_reference_uid,
        meta=meta,
    )
