"""Faults a test queues for a mock controller's next frames (shared by every link's mock)."""

from __future__ import annotations

import math
import threading


class QueuedFaults:
    """Raw bytes to send before the next frame, and NaN joints for the next few joint frames.

    Thread-safe: tests call :meth:`inject_raw` / :meth:`inject_nan` from their own thread while the
    mock's event loop takes them.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._raw: list[bytes] = []
        self._nan_frames = 0
        self._nan_joint = 0

    def inject_raw(self, data: bytes) -> None:
        """Send ``data`` verbatim before the next frame (garbage, an oversized prefix…)."""
        with self._lock:
            self._raw.append(bytes(data))

    def inject_nan(self, n_frames: int = 1, joint: int = 0) -> None:
        """Replace joint ``joint`` by NaN in the next ``n_frames`` joint frames."""
        with self._lock:
            self._nan_frames = n_frames
            self._nan_joint = joint

    def take_raw(self) -> list[bytes]:
        """Every queued raw chunk, oldest first; the queue is emptied."""
        with self._lock:
            out, self._raw = self._raw, []
        return out

    def next_raw(self) -> bytes | None:
        """The oldest queued raw chunk, or None."""
        with self._lock:
            return self._raw.pop(0) if self._raw else None

    def joints(self, joints_rad: tuple[float, ...] | list[float]) -> list[float]:
        """``joints_rad`` as sent in the next joint frame: with a NaN while one is queued."""
        q = list(joints_rad)
        with self._lock:
            if self._nan_frames > 0:
                q[self._nan_joint] = math.nan
                self._nan_frames -= 1
        return q
