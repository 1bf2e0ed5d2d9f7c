"""The OpenIGTLink publisher: the service's registration and live tool pose to navigation (``[igtl]``).

:class:`service.navigation.igtl.server.IgtlServer` on the service loop, fed from the current registration
(plus
the last refusal), the live joints and link health, the robot model's forward kinematics and
``igtl.tool0_from_tcp``.  It listens to :class:`~service.events.RegistrationDone` and
:class:`~service.events.RegistrationRefused` and :class:`~service.events.RegistrationWithdrawn`
(bound by :mod:`service.runtime.assembly`) and pushes at once;
otherwise every ``igtl.period_s``.  It publishes ``igtl_client_connected`` /
``igtl_client_disconnected`` / ``igtl_client_header_version`` (the client sent a version-2 message:
answered in version 2 from then on).
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING, Any, Final

import numpy as np

from registration.arrays import F64
from registration.model.kinematics import sphere_centres_robot_mm
from service.events import (
    IgtlClientConnected,
    IgtlClientDisconnected,
    IgtlClientHeaderVersion,
    Publish,
    RegistrationDone,
    RegistrationRefused,
    RegistrationWithdrawn,
    VerificationDone,
)
from service.navigation.igtl.server import (
    IgtlServer,
    IgtlStateSource,
    JointView,
    Refusal,
    RegistrationState,
    RegistrationView,
    SpherePoint,
)
from service.records import RegistrationRecord
from service.registrations.evidence import evidence_of

log = logging.getLogger(__name__)

if TYPE_CHECKING:
    from drivers.base import RobotLink
    from registration.model.kinematics import RobotModel
    from service.intake.capture import Capture
    from service.registrations.orchestrator import Orchestrator
    from service.settings import IgtlSettings

REASON_MAX_CHARS: Final = 400
"""Longest ``Reason`` (and STATUS text) sent to navigation, characters: a reader's status line, not a
log.  A longer one is cut at a word and points to ``GET /status`` (``listeners.igtl.reasons``), which
holds the whole text."""
FULL_TEXT_NOTE: Final = " … (full text: GET /status, listeners.igtl.reasons)"


def cut_at_word(text: str, limit: int = REASON_MAX_CHARS) -> str:
    """``text`` if it fits in ``limit`` characters, else cut at the last word boundary that leaves room
    for :data:`FULL_TEXT_NOTE` (never mid-word unless one word fills half the room)."""
    if len(text) <= limit:
        return text
    room = limit - len(FULL_TEXT_NOTE)
    head = text[:room]
    space = head.rfind(" ")
    if space > room // 2:
        head = head[:space]
    return head.rstrip(" ,;:(") + FULL_TEXT_NOTE


def joint_view(
    joints_rad: tuple[float, ...],
    t_s: float,
    link_state: str,
    link_reason: str,
    now_t_s: float,
    max_age_s: float,
) -> JointView:
    """The joints as ``ToolToImage`` judges them: one freshness limit, ``igtl.joint_max_age_s``,
    named in the reason.  A link the driver calls ``stale`` by its own rule (three frame periods,
    60 ms at 50 Hz) is fresh here while its last sample is younger than ``max_age_s``; a link that is
    ``down`` stays down."""
    if link_state in ("connected", "stale"):
        age_s = now_t_s - t_s
        if age_s <= max_age_s:
            link_state, link_reason = "connected", "receiving joint frames"
        else:
            link_state = "stale"
            link_reason = f"no joint sample for {age_s:.3f} s (> igtl.joint_max_age_s = {max_age_s:g} s)"
    return JointView(joints_rad, t_s, link_state, cut_at_word(link_reason))


_CLIENT_EVENTS = {
    "connected": IgtlClientConnected,
    "disconnected": IgtlClientDisconnected,
    "header_version": IgtlClientHeaderVersion,
}


class IgtlPublisher:
    """The OpenIGTLink server and its state source (see the module docstring)."""

    def __init__(
        self,
        settings: IgtlSettings,
        orchestrator: Orchestrator,
        capture: Capture,
        robot_link: RobotLink,
        robot_model: RobotModel,
        publish: Publish,
    ) -> None:
        self.settings = settings
        self.orchestrator = orchestrator
        self.capture = capture
        self.robot_link = robot_link
        self.publish = publish
        self._last_refusal: Refusal | None = None
        self._reasons: dict[str, str] = {}
        """The whole texts behind what was cut for the wire (``GET /status``, ``listeners.igtl.reasons``)."""
        self._view: tuple[RegistrationRecord, RegistrationView] | None = None
        source = IgtlStateSource(
            registration=self._registration_state,
            joints=self._joints,
            robot_from_tool0=lambda q: robot_model.robot_from_tool0(
                robot_model.at_limits(q, robot_link.joint_resolution_rad(q))
            ),  # a joint within the wire's rounding of a limit is at it
            tool0_from_tcp=settings.tool0_from_tcp.matrix(),
        )
        self.server = IgtlServer(settings, source, on_client=self._on_client)

    async def start(self) -> None:
        await self.server.start()

    async def stop(self) -> None:
        await self.server.stop()

    def status(self) -> dict[str, Any]:
        """For ``GET /status`` (``listeners.igtl``)."""
        g, s = self.settings, self.server
        return {
            "enabled": g.enabled, "host": g.host, "port": s.port, "clients": s.client_count,
            "counters": dict(s.counters),
            "peers": s.client_info(),  # per client: peer and header version
            "reasons": dict(self._reasons),  # the whole texts of what navigation was sent cut
        }  # fmt: skip

    # ---- bus listeners (the publishing thread) --------------------------------------------

    def on_registration_done(self, event: RegistrationDone) -> None:
        """Push the new current registration."""
        self._last_refusal = None
        self.server.notify()

    def on_registration_refused(self, event: RegistrationRefused) -> None:
        """Push the refusal (the current registration, if any, stays)."""
        self._last_refusal = Refusal(str(event.registration_id), cut_at_word(event.reason))
        self._reasons["last_refusal"] = event.reason
        self.server.notify()

    def on_verification_done(self, event: VerificationDone) -> None:
        """Push at once: a passing verification at another pose raises the evidence level."""
        if event.passed:
            self.server.notify()

    def on_registration_withdrawn(self, event: RegistrationWithdrawn) -> None:
        """Push at once when the current registration was withdrawn (a failed verification, a changed
        scan): every client must see INVALID now, not at the next ``igtl.period_s``."""
        if event.was_current:
            self.server.notify()

    def _on_client(self, event: str, peer: str, n_clients: int, header_version: int) -> None:
        self.publish(_CLIENT_EVENTS[event](peer=peer, clients=n_clients, header_version=header_version))

    # ---- state source (service loop) ------------------------------------------------------

    def _registration_state(self) -> RegistrationState:
        """The orchestrator's current registration; anything not accepted-and-current (withdrawn,
        retired, none) is INVALID with the orchestrator's reason (``no_current_reason``)."""
        orch = self.orchestrator
        cur = orch.current
        if cur is None or cur.image_from_robot is None or cur.status != "accepted" or cur.withdrawn_at:
            why = (
                orch.no_current_reason
                if cur is None
                else f"registration {cur.id} is {cur.status}: {cur.reason}"
            )
            self._reasons["registration"] = why
            return RegistrationState(None, self._last_refusal, cut_at_word(why))
        self._reasons.pop("registration", None)
        cached = self._view
        if cached is None or cached[0] is not cur:
            cached = self._view = (cur, self._make_view(cur))
        return RegistrationState(cached[1], self._last_refusal)

    def _make_view(self, cur: RegistrationRecord) -> RegistrationView:
        fig = cur.figures
        tre = fig.predicted_tre_mm if fig is not None else ()
        image_from_robot = np.asarray(cur.image_from_robot, dtype=np.float64)
        return RegistrationView(
            image_from_robot=image_from_robot,
            registration_id=str(cur.id),
            fre_mm=float(cur.fre_mm or 0.0),
            tre_pred_mm=max(tre) if tre else None,
            chain_error_mm=None if fig is None else fig.predicted_chain_error_mm,
            chain_error_source="" if fig is None else fig.chain_error_source,
            evidence="" if (ev := evidence_of(cur)) is None else ev.level,
            spheres=self._spheres(cur, image_from_robot),
            sphere_diameter_mm=float(self.orchestrator.phantom.sphere_diameter_mm),
        )

    def _spheres(self, cur: RegistrationRecord, image_from_robot: F64) -> tuple[SpherePoint, ...]:
        """Each matched sphere's centre as the registration maps it into the image (LPS, mm):
        ``image_from_robot`` applied to its robot-frame centre at the scan's joints."""
        orch = self.orchestrator
        if cur.figures is None or not cur.joints_rad or not cur.figures.spheres:
            return ()
        try:
            robot_mm = sphere_centres_robot_mm(
                orch.robot_model, cur.joints_rad, orch.tool0_from_phantom, orch.phantom.centres_phantom_mm
            )
        except Exception:  # the POINT list is a view: a failure here must not stop the transforms
            log.exception("OpenIGTLink: the sphere centres of registration %d could not be computed", cur.id)
            return ()
        out = []
        for s in cur.figures.spheres:
            p = image_from_robot[:3, :3] @ robot_mm[s.robot_index] + image_from_robot[:3, 3]
            out.append(SpherePoint(s.sphere, (float(p[0]), float(p[1]), float(p[2])), float(s.residual_mm)))
        return tuple(out)

    def _joints(self) -> JointView | None:
        latest = self.capture.latest()
        if latest is None:
            return None
        h = self.robot_link.health()
        view = joint_view(
            tuple(float(v) for v in latest.joints_rad), float(latest.t_s), str(h.state), str(h.reason),
            time.monotonic(), self.settings.joint_max_age_s,
        )  # fmt: skip
        if view.health == "connected":
            self._reasons.pop("joints", None)
        else:
            self._reasons["joints"] = str(h.reason) if h.state == "down" else view.reason
        return view
