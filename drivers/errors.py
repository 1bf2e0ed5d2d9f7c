"""Robot-link errors.

``drivers`` may not import ``registration`` (design.md §2), so this family has
its own base; it carries the same ``exit_code`` / ``http_status`` / ``title``
attributes as :class:`registration.errors.OarmRegError`, and the service and CLI
map both families the same way.
"""

from __future__ import annotations

EXIT_ROBOT_LINK = 5


class RobotLinkError(Exception):
    """The robot controller link failed or is unusable."""

    exit_code: int = EXIT_ROBOT_LINK
    http_status: int = 409
    title: str = "Robot link error"


class LinkConfigError(RobotLinkError):
    """A link URL or register map is malformed."""

    exit_code = 3
    http_status = 422
    title = "Invalid robot link configuration"


class LinkTimeoutError(RobotLinkError):
    """No connection or no data within the allowed time."""

    title = "Robot link timeout"


class ProtocolError(RobotLinkError):
    """The peer sent bytes that violate the protocol."""

    title = "Robot link protocol error"
