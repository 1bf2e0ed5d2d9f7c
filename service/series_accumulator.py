"""Decode a C-STORE series slice by slice as it arrives, so the volume is ready at association release.

The DICOM Storage SCP (:mod:`service.dicom_scp`) writes each instance to disk and hands its path
here; a worker thread reads its header and pixel data with the same functions the series loader
uses (:mod:`registration.dicom`: the header pass :func:`~registration.dicom.headers.read_headers`,
the HU rescale :func:`~registration.dicom.pixels.read_voxels`, and the geometry checks of
:func:`~registration.dicom.check_series_geometry` — one Frame of Reference, one image
size and orientation, contiguous evenly spaced positions).  At release :meth:`SeriesAccumulator.assemble`
waits for the last decodes, runs the checks on every slice and stacks the volume in slice order.

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

from registration.volume import Volume

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class _Decoded:
    headers: tuple[Any, ...]
    """:class:`registration.dicom.SliceHeader` of each frame of the file."""
    voxels: NDArray[Any]
    """(n_frames, rows, columns) HU."""


def _decode(path: Path) -> _Decoded | None:
    """Header + HU pixels of one file, or None when the loader would skip it (then the loader decides)."""
    from registration.dicom import SkippedFile
    from registration.dicom.headers import read_headers
    from registration.dicom.pixels import read_voxels

    result = read_headers(path)
    if isinstance(result, SkippedFile) or not result:
        return None
    voxels = read_voxels(result, result[0].series_uid)
    return _Decoded(tuple(result), voxels)


class SeriesAccumulator:
    """The instances of one series folder received so far, decoded on ``executor``.

    Thread-safe: :meth:`add` runs on pynetdicom's association thread, :meth:`assemble` on a
    service worker thread.
    """

    def __init__(self, series_dir: Path, executor: Executor) -> None:
        self.series_dir = series_dir
        self._executor = executor
        self._lock = threading.Lock()
        self._futures: dict[Path, Future[_Decoded | None]] = {}
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
            self._futures[path] = self._executor.submit(_decode, path)

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
        if set(decoded) != on_disk or any(
            h.series_uid != series_uid for d in decoded.values() for h in d.headers
        ):
            return load_series(self.series_dir, series_uid=series_uid)
        return _stack(self.series_dir, series_uid, decoded)


def _stack(root: Path, series_uid: str, decoded: dict[Path, _Decoded]) -> Volume:
    """Check the geometry of every slice and stack the decoded frames in slice order."""
    from registration.dicom import check_series_geometry
    from registration.dicom.loader import _volume_meta  # the loader's own meta, key for key

    frames: dict[tuple[Path, int], NDArray[Any]] = {}
    headers = []
    for d in decoded.values():
        for h, plane in zip(d.headers, d.voxels, strict=True):
            frames[(h.path, h.frame)] = plane
            headers.append(h)
    geometry = check_series_geometry(headers, series_uid)
    dtype = np.result_type(*{plane.dtype for plane in frames.values()})
    voxels = np.stack([frames[(h.path, h.frame)] for h in geometry.slices]).astype(dtype, copy=False)
    first = geometry.slices[0]
    meta: dict[str, Any] = {**_volume_meta(root, geometry, ()), "decoded_on_arrival": True}
    return Volume(
        voxels=voxels,
        image_from_voxel=geometry.image_from_voxel,
        series_uid=series_uid,
        frame_of_reference_uid=first.frame_of_reference_uid,
        meta=meta,
    )
