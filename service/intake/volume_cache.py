"""The last few loaded volumes, so ``POST /register`` need not re-read a scan the watcher just loaded."""

from __future__ import annotations

import threading
from collections import OrderedDict

from registration.errors import DicomSeriesError
from registration.imaging.volume import Volume
from service.records import ScanRecord

VOLUME_CACHE_SIZE = 2
"""Loaded volumes kept in memory (a 512 × 512 × 192 int16 scan is 100 MB)."""


class VolumeCache:
    """A thread-safe LRU of loaded volumes keyed by SeriesInstanceUID."""

    def __init__(self, size: int = VOLUME_CACHE_SIZE) -> None:
        self._size = size
        self._volumes: OrderedDict[str, Volume] = OrderedDict()
        self._lock = threading.Lock()

    def put(self, series_uid: str, volume: Volume) -> None:
        with self._lock:
            self._volumes[series_uid] = volume
            self._volumes.move_to_end(series_uid)
            while len(self._volumes) > self._size:
                self._volumes.popitem(last=False)

    def discard(self, series_uid: str) -> None:
        """Forget a volume (its series was reopened or its files deleted)."""
        with self._lock:
            self._volumes.pop(series_uid, None)

    def get(self, series_uid: str) -> Volume | None:
        with self._lock:
            return self._volumes.get(series_uid)

    def load(self, scan: ScanRecord) -> Volume:
        """The scan's volume, from the cache or read again from its folder.

        Raises
        ------
        DicomSeriesError
            The series can no longer be read (files moved or deleted).
        """
        vol = self.get(scan.series_uid)
        if vol is not None:
            return vol
        from registration.dicom import load_series

        try:
            vol = load_series(scan.folder, series_uid=scan.series_uid)
        except OSError as e:
            raise DicomSeriesError(
                f"series {scan.series_uid} can no longer be read from {scan.folder}: {e}; re-export the scan"
            ) from None
        self.put(scan.series_uid, vol)
        return vol
