"""Joint capture: hold the robot link open and record the joints at each scan's arrival.

The link (``drivers.factory.open_link``) reads on its own thread, keeps a ≥ 60 s ring
buffer of timestamped joint states and owns the service's **one reconnect policy**:
capped exponential back-off while the controller is unreachable or after any failure,
configured on the link URL (``backoff_initial_s``, ``backoff_max_s``, seconds; see
docs/robot-link.md).  :class:`Capture` only starts the link (never retries by itself),
watches its health and publishes ``link_state`` events on every change.
:meth:`Capture.snapshot` (thread-safe) takes the joints at a scan's arrival and asks
:func:`registration.model.stillness.assess_stillness` whether the robot was still over
``stillness.window_s`` before the first file appeared and until the last file landed.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from dataclasses import replace
from datetime import UTC, datetime
from typing import Any

import numpy as np

from drivers.base import RobotLink
from service.events import LinkState, Publish
from service.records import JointSnapshot, stillness_verdict
from service.settings import Settings

log = logging.getLogger(__name__)

HEALTH_POLL_S = 0.1
"""Link-health sampling period for ``link_state`` events (5 joint frames at 50 Hz)."""

LATE_FRAME_WAIT_S = 0.5
"""A snapshot of a streamed link waits up to this long for the first frame stamped after the
window end, so frames received before the end but not yet handed to the history (a busy process)
are counted.  Twice the default ``stillness.max_gap_s``; a stopped stream costs this once."""

PERIOD_HISTORY_S = 60.0
"""Span of the session's history from which a streamed link's long-run frame period is measured (s),
frames over span (:func:`registration.model.stillness.stream_period_s`)."""


def _on_event_loop() -> bool:
    try:
        asyncio.get_running_loop()
    except RuntimeError:
        return False
    return True


class Capture:
    """Owner of the robot link inside the service.

    Parameters
    ----------
    link : RobotLink
        Built by ``drivers.factory.open_link`` (never connected yet) or injected by tests.
    settings : Settings
        ``robot.connect_timeout_s``: after this long without a joint frame a warning is logged
        (the link keeps trying).
    publish : callable
        ``publish(event)``; thread-safe (``EventBus.publish``).
    """

    def __init__(self, link: RobotLink, settings: Settings, publish: Publish) -> None:
        self.link = link
        self.settings = settings
        self.publish = publish
        self._task: asyncio.Task[None] | None = None
        self._last_state: tuple[str, str] | None = None
        self._connected_since_t_s: float | None = None
        self._bad_since_t_s: float | None = time.monotonic()
        """Since when the reported state has not been ``connected`` (None while it is)."""
        self._model: Any = None

    @property
    def url(self) -> str:
        return str(self.link.url)

    # ---- lifecycle ------------------------------------------------------------------------

    async def start(self) -> None:
        """Start the link's reader (it connects and reconnects by itself) and the health watch."""
        self._bad_since_t_s = time.monotonic()
        self.link.start()
        self._task = asyncio.create_task(self._supervise(), name="oarmreg-capture")

    async def stop(self) -> None:
        """Stop the health watch and close the link (bounded by the link's ``close_timeout_s``)."""
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        try:
            await self.link.close()
        except Exception:
            log.exception("robot link %s: close failed", self.url)

    async def _supervise(self) -> None:
        warn_at_t_s: float | None = time.monotonic() + self.settings.robot.connect_timeout_s
        while True:
            self._check_state()
            if warn_at_t_s is not None and self.link.latest() is None and time.monotonic() > warn_at_t_s:
                warn_at_t_s = None
                log.warning(
                    "robot link %s: no joint frame %.3g s after start (%s); still trying",
                    self.url, self.settings.robot.connect_timeout_s, self.link.health().reason,
                )  # fmt: skip
            await asyncio.sleep(HEALTH_POLL_S)

    def _check_state(self) -> None:
        h = self.health()
        if h["state"] == "connected":
            self._bad_since_t_s = None
        elif self._bad_since_t_s is None:
            self._bad_since_t_s = time.monotonic()
        key = (h["state"], h["state"] if h["state"] != "down" else h["reason"][:80])
        if key != self._last_state:
            prev = self._last_state[0] if self._last_state else None
            self._last_state = key
            if h["state"] == "connected" and prev != "connected":
                self._connected_since_t_s = time.monotonic()
            self.publish(LinkState(url=self.url, state=str(h["state"]), reason=str(h["reason"])))

    # ---- queries (any thread) -------------------------------------------------------------

    def health(self) -> dict[str, Any]:
        """``{"url", "state": connected|stale|down, "reason", "last_frame_age_s", "history_s",
        "max_receive_gap_s"}`` (the largest time between two received frames, the later within the
        last :data:`PERIOD_HISTORY_S`, by the receive clock).

        ``stale`` means no frame for ``robot.stale_after_s`` (not the link's own 3 frame periods,
        which flap under ordinary load); ``down`` is the link's.
        """
        h = self.link.health()
        counters = self.link.counters()
        latest = self.link.latest()
        now = time.monotonic()
        # from the ring without copying it: a copy of 120 s at 1 kHz every HEALTH_POLL_S cost 22 ms
        gap_s = self.link.max_receive_gap_s(now - PERIOD_HISTORY_S)
        span = self.link.history_span_s(now - self.settings.stillness.window_s * 4)
        state, reason, age = h.state, h.reason, h.last_frame_age_s
        limit_s = self.settings.robot.stale_after_s
        if state != "down" and age is not None and latest is not None:
            state, reason = (
                ("connected", "receiving joint frames")
                if age <= limit_s
                else (
                    "stale",
                    f"no valid joint frame for {age:.3f} s (> robot.stale_after_s = {limit_s:g} s)",
                )
            )
        status = self.link.status()
        return {
            "url": self.url,
            "state": state,
            "reason": reason,
            "last_frame_age_s": age if latest is not None else None,
            "history_s": float(span),
            "max_receive_gap_s": gap_s,
            # the controller's last STATUS in_motion (TriState 1 / 0 / −1): true, false, or None (unknown,
            # or no STATUS yet); a TRUE inside a scan's window refuses it as moved
            "in_motion": None if status is None or status.in_motion not in (0, 1) else status.in_motion == 1,
            **{k: int(counters.get(k, 0)) for k in ("down_events", "connect_failures")},
        }

    def problem(self) -> str | None:
        """What is wrong with the link once it has not been ``connected`` for ``health.link_hold_off_s``
        (None: connected, or not for that long yet)."""
        h = self.health()
        since = self._bad_since_t_s
        hold_s = self.settings.health.link_hold_off_s
        if h["state"] == "connected" or since is None or time.monotonic() - since <= hold_s:
            return None
        return (
            f"the robot link {self.url} has been {h['state']} for {time.monotonic() - since:.1f} s "
            f"(> health.link_hold_off_s = {hold_s:g} s): {h['reason']}; no scan can be registered until it "
            "is connected: check the controller, its VAL3 program and the cable"
        )

    def latest(self) -> Any:
        return self.link.latest()

    def snapshot(
        self, first_seen_t_s: float, last_change_t_s: float, *, preexisting: bool = False
    ) -> JointSnapshot:
        """Joints at a scan's arrival and the stillness verdict, one typed record for the database.

        The window runs from ``stillness.window_s`` before ``first_seen_t_s`` (the first file of the
        series appeared) to ``last_change_t_s`` (the last file landed), monotonic seconds.
        """
        from registration.model.stillness import CATCH_UP_S, assess_stillness

        st = self.settings.stillness
        h = self.health()
        unknown = JointSnapshot(
            captured_at=datetime.now(UTC).isoformat(),
            link_url=self.url,
            link_state=h["state"],
            link_reason=h["reason"],
            window_s=st.window_s,
            verdict="incomplete",
            covered_s=0.0,
        )
        if preexisting:
            return replace(
                unknown,
                stillness_reason=(
                    "joint history incomplete: the series was already in the watch folder when the service "
                    "started, so the joint angles during its acquisition are unknown; re-export or rescan "
                    "it while the service runs"
                ),
            )
        start_t = first_seen_t_s - st.window_s
        link = self.link
        streamed = link.streamed
        if streamed and h["state"] != "down" and not _on_event_loop():
            link.wait_past(last_change_t_s, LATE_FRAME_WAIT_S)
        samples = link.history(start_t - st.max_gap_s)
        after_s = max(st.max_gap_s, CATCH_UP_S)  # the judge looks for a gap's late frames this far
        samples = [s for s in samples if s.t_s <= last_change_t_s + after_s]
        if not samples:
            return replace(
                unknown,
                stillness_reason=(
                    f"joint history incomplete: no joint samples from {self.url} between {st.window_s:g} s "
                    f"before the scan arrived and its last file; the robot link is {h['state']} "
                    f"({h['reason']})"
                ),
            )
        # the joints "at arrival": the last sample at or before the first file, else the first after it
        before = [s for s in samples if s.t_s <= first_seen_t_s]
        at = before[-1] if before else samples[0]
        inside = [s for s in samples if start_t <= s.t_s <= last_change_t_s]
        sessions = {x.number: x for x in link.sessions()}
        first_session = sessions.get(inside[0].session) if inside else None
        period_s = self._stream_period_s(inside[-1], last_change_t_s) if streamed and inside else None
        t = np.array([s.t_s for s in samples], dtype=np.float64)
        q = np.array([s.joints_rad for s in samples], dtype=np.float64)
        window_s = last_change_t_s - start_t
        res = assess_stillness(
            t,
            q,
            window_end_t_s=last_change_t_s,
            window_s=window_s,
            max_deviation_rad=st.max_deviation_rad,
            max_gap_s=st.max_gap_s,
            watched_from_t_s=first_session.connected_t_s if first_session is not None else None,
            sessions=np.array([s.session for s in samples], dtype=np.int64),
            period_s=period_s,
            in_motion_t_s=self._in_motion_t_s(start_t, last_change_t_s),
        )
        return replace(
            unknown,
            verdict=stillness_verdict(res.verdict),
            joints_rad=self._at_limits(at.joints_rad),
            joints_received_at=at.received_at.isoformat(),
            max_deviation_rad=float(res.max_deviation_rad),
            covered_s=float(res.covered_s),
            n_samples=int(res.n_samples),
            stillness_reason=str(res.reason),
        )

    def _at_limits(self, joints_rad: tuple[float, ...]) -> tuple[float, ...]:
        """The joints, each value within the link's wire rounding of a joint limit
        (``joint_resolution_rad``: float32 over simple_message, the serial text's digits, the Modbus
        register type) put at that limit: the registration's limit check then sees the limit the arm
        stands at, not the wire's rounding of it.  Values farther out are left for it to
        refuse."""
        q = tuple(float(v) for v in joints_rad)
        model = self._limits_model()
        if model is None:
            return q
        return tuple(float(v) for v in model.at_limits(q, self.link.joint_resolution_rad(q)))

    def _limits_model(self) -> Any:
        """The configured robot model (for its joint limits), loaded once; None if it cannot be (the
        registration reports that itself)."""
        if self._model is None:
            from registration.errors import ConfigError
            from registration.model.kinematics import RobotModel

            try:
                self._model = RobotModel.load(self.settings.robot.model)
            except ConfigError:
                self._model = False
        return self._model or None

    def _in_motion_t_s(self, start_t_s: float, end_t_s: float) -> list[float]:
        """Receive times of the controller statuses in ``[start_t_s, end_t_s]`` reporting ``in_motion``
        = TRUE (a link whose controller sends no status gives none)."""
        history = self.link.status_history(start_t_s)
        return [s.t_s for s in history if s.t_s <= end_t_s and s.in_motion == 1]

    def _stream_period_s(self, last: Any, end_t_s: float) -> float | None:
        """The long-run frame period of ``last``'s session over :data:`PERIOD_HISTORY_S` (None: too few)."""
        from registration.model.stillness import stream_period_s

        same = [s.t_s for s in self.link.history(end_t_s - PERIOD_HISTORY_S) if s.session == last.session]
        return stream_period_s(same)
