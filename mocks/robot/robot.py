"""A scriptable 6-axis robot for the mock controllers.

:class:`ScriptedRobot` is a joint-space timeline: it holds a pose, or moves
to a target over a given duration with a smooth (minimum-jerk, quintic)
profile.  Every mock server samples ``joints_rad_at(time.monotonic())``, so the
same robot can be served over simple_message, Modbus and serial at once.
Thread-safe: tests and scripts call it from one thread while servers sample it
from another.

Script files (JSON or TOML) list steps that run one after another from the
moment the script is started::

    # TOML                                   // JSON
    initial_deg = [0, 0, 90, 0, 45, 0]       {"initial_deg": [0, 0, 90, 0, 45, 0],
    [[steps]]                                 "steps": [{"hold_s": 1.0},
    hold_s = 1.0                                        {"move_to_deg": [10, 0, 90, 0, 45, 0],
    [[steps]]                                            "duration_s": 2.0}],
    move_to_deg = [10, 0, 90, 0, 45, 0]       "loop": false}
    duration_s = 2.0

A step is ``{"hold_s": T}``, ``{"move_to_deg": [...], "duration_s": T}`` or
``{"move_to_rad": [...], "duration_s": T}``; ``loop = true`` repeats the steps.
"""

from __future__ import annotations

import json
import math
import threading
import time
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

N_JOINTS = 6
HOME_RAD = (0.0, 0.0, math.pi / 2, 0.0, math.pi / 4, 0.0)
"""Default pose: forearm horizontal, wrist tilted (well inside every TX60 / TX2-60 limit)."""


@dataclass(frozen=True)
class _Segment:
    t0_s: float
    t1_s: float
    q0: tuple[float, ...]
    q1: tuple[float, ...]

    def at(self, t_s: float) -> tuple[float, ...]:
        if t_s >= self.t1_s or self.t1_s <= self.t0_s:
            return self.q1
        s = max(0.0, (t_s - self.t0_s) / (self.t1_s - self.t0_s))
        b = s * s * s * (10.0 - 15.0 * s + 6.0 * s * s)  # minimum-jerk blend 0 → 1
        return tuple(a + (c - a) * b for a, c in zip(self.q0, self.q1, strict=True))

    @property
    def moving(self) -> bool:
        return self.q0 != self.q1


@dataclass(frozen=True)
class ControllerStatus:
    """What STATUS (msg 13) reports; TriState −1/0/1, mode 1 manual / 2 auto."""

    drives_powered: int = 1
    e_stopped: int = 0
    error_code: int = 0
    in_error: int = 0
    mode: int = 2
    motion_possible: int = 1
    in_motion: int | None = None
    """None: reported from the timeline (1 while a move runs, else 0); −1 / 0 / 1: reported as is,
    whatever the joints do (a controller that says it moves while its joints stand still)."""


class ScriptedRobot:
    """A thread-safe joint-space timeline.

    Parameters
    ----------
    initial_rad : sequence of 6 float
        Pose held until told otherwise.
    """

    def __init__(self, initial_rad: Sequence[float] = HOME_RAD) -> None:
        q = _check_q(initial_rad)
        self._lock = threading.Lock()
        self._segments: list[_Segment] = []
        self._hold_q = q
        self._loop_steps: list[dict[str, Any]] | None = None
        self.controller_status = ControllerStatus()

    # ---- commands ----------------------------------------------------------

    def hold(self, joints_rad: Sequence[float] | None = None) -> None:
        """Stop now and hold the current pose (or jump to ``joints_rad``)."""
        now = time.monotonic()
        with self._lock:
            q = self._at_locked(now) if joints_rad is None else _check_q(joints_rad)
            self._segments = []
            self._hold_q = q
            self._loop_steps = None

    def move_to(
        self, joints_rad: Sequence[float], duration_s: float, *, start_t_s: float | None = None
    ) -> None:
        """Start now (or at ``start_t_s``) a smooth move from the current pose to ``joints_rad``."""
        if not duration_s > 0:
            raise ValueError(f"duration_s must be > 0, got {duration_s}")
        target = _check_q(joints_rad)
        t0 = time.monotonic() if start_t_s is None else start_t_s
        with self._lock:
            q0 = self._at_locked(t0)
            self._segments = [s for s in self._segments if s.t1_s <= t0]
            self._segments.append(_Segment(t0, t0 + duration_s, q0, target))
            self._loop_steps = None

    def queue_move(self, joints_rad: Sequence[float], duration_s: float) -> None:
        """Append a move after the last queued step."""
        self._queue(_check_q(joints_rad), duration_s)

    def queue_hold(self, duration_s: float) -> None:
        """Append a pause after the last queued step."""
        self._queue(None, duration_s)

    def _queue(self, target: tuple[float, ...] | None, duration_s: float) -> None:
        if not duration_s >= 0:
            raise ValueError(f"duration_s must be >= 0, got {duration_s}")
        now = time.monotonic()
        with self._lock:
            t0 = max(now, self._segments[-1].t1_s) if self._segments else now
            q0 = self._at_locked(t0)
            self._segments.append(_Segment(t0, t0 + duration_s, q0, q0 if target is None else target))

    def run_script(self, script: dict[str, Any] | str | Path) -> None:
        """Replace the timeline by a script (a dict or a JSON / TOML file, see the module doc)."""
        d = load_script(script) if isinstance(script, (str, Path)) else script
        if "initial_deg" in d:
            self.hold([math.radians(v) for v in d["initial_deg"]])
        elif "initial_rad" in d:
            self.hold(d["initial_rad"])
        steps = list(d.get("steps", []))
        self._enqueue_steps(steps)
        if d.get("loop"):
            with self._lock:
                self._loop_steps = steps

    def _enqueue_steps(self, steps: list[dict[str, Any]]) -> None:
        for i, st in enumerate(steps):
            if "hold_s" in st:
                self.queue_hold(float(st["hold_s"]))
            elif "move_to_deg" in st:
                self.queue_move([math.radians(v) for v in st["move_to_deg"]], float(st["duration_s"]))
            elif "move_to_rad" in st:
                self.queue_move(st["move_to_rad"], float(st["duration_s"]))
            else:
                raise ValueError(f"script step {i}: expected hold_s, move_to_deg or move_to_rad, got {st}")

    # ---- sampling ----------------------------------------------------------

    def joints_rad_at(self, t_s: float | None = None) -> tuple[float, ...]:
        """Joint angles (rad) at ``time.monotonic()`` time ``t_s`` (default now)."""
        t = time.monotonic() if t_s is None else t_s
        with self._lock:
            self._extend_loop_locked(t)
            return self._at_locked(t)

    def in_motion_at(self, t_s: float | None = None) -> bool:
        t = time.monotonic() if t_s is None else t_s
        with self._lock:
            return any(s.moving and s.t0_s <= t < s.t1_s for s in self._segments)

    def reported_in_motion(self, t_s: float | None = None) -> int:
        """STATUS ``in_motion`` (TriState): :attr:`ControllerStatus.in_motion` if set, else the timeline's."""
        forced = self.controller_status.in_motion
        return int(self.in_motion_at(t_s)) if forced is None else int(forced)

    def motion_end_t_s(self) -> float:
        """When the last queued step ends (``time.monotonic()`` seconds; now if idle)."""
        with self._lock:
            return max([time.monotonic()] + [s.t1_s for s in self._segments])

    def _at_locked(self, t: float) -> tuple[float, ...]:
        q = self._hold_q
        for s in self._segments:
            if t < s.t0_s:
                break
            q = s.at(t)
        return q

    def _extend_loop_locked(self, t: float) -> None:
        steps = self._loop_steps
        if not steps or (self._segments and self._segments[-1].t1_s > t):
            return
        # re-queue the steps (inline version of _enqueue_steps; the lock is held)
        t0 = max(t, self._segments[-1].t1_s) if self._segments else t
        q = self._at_locked(t0)
        self._segments = []
        self._hold_q = q
        for st in steps:
            d = float(st.get("hold_s", st.get("duration_s", 0.0)))
            if "move_to_deg" in st:
                target = _check_q([math.radians(v) for v in st["move_to_deg"]])
            elif "move_to_rad" in st:
                target = _check_q(st["move_to_rad"])
            else:
                target = q
            self._segments.append(_Segment(t0, t0 + d, q, target))
            t0, q = t0 + d, target


def load_script(path: str | Path) -> dict[str, Any]:
    """Read a robot script from a ``.json`` or ``.toml`` file."""
    p = Path(path)
    text = p.read_text(encoding="utf-8")
    if p.suffix.lower() == ".toml":
        return tomllib.loads(text)
    d = json.loads(text)
    if not isinstance(d, dict):
        raise ValueError(f"{p}: a robot script must be a JSON object with 'steps'")
    return d


def _check_q(q: Sequence[float]) -> tuple[float, ...]:
    t = tuple(float(v) for v in q)
    if len(t) != N_JOINTS:
        raise ValueError(f"expected {N_JOINTS} joint values, got {len(t)}")
    return t
