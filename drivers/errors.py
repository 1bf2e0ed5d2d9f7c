"""Robot-link errors.

``drivers`` may not import ``registration`` (design.md §2), so this family has
its own base.  Like :class:`registration.errors.OarmRegError` it carries only a
``title``; the service maps both families to HTTP status and exit code in one
table (:mod:`service.error_map`).
"""

from __future__ import annotations


class RobotLinkError(Exception):
    """The robot controller link failed or is unusable."""

    title: str = "Robot link error"


class LinkConfigError(RobotLinkError):
    """A link URL or register map is malformed."""

    title = "Invalid robot link configuration"


class LinkTimeoutError(RobotLinkError):
    """No connection or no data within the allowed time."""

    title = "Robot link timeout"


class ProtocolError(RobotLinkError):
    """The peer sent bytes that violate the protocol."""

    title = "Robot link protocol error"
