"""What exists before the service starts: validated settings, the loaded phantom and robot model,
the robot link (not connected yet) and the bus (:class:`~service.runtime.context.ServiceInputs`).

Whatever can fail early fails here, naming the setting: a bad phantom file, robot model or link URL.
"""

from __future__ import annotations

from drivers.base import RobotLink
from registration.model.kinematics import RobotModel
from registration.model.phantom import Phantom
from service.event_bus import EventBus
from service.runtime.context import ServiceInputs
from service.settings import Settings


def prepare_inputs(
    settings: Settings,
    *,
    robot_link: RobotLink | None = None,
    phantom: Phantom | None = None,
    robot_model: RobotModel | None = None,
) -> ServiceInputs:
    """Check the settings and load what the service needs before start-up.

    Parameters
    ----------
    settings : Settings
        From :func:`service.settings.load_settings`.
    robot_link : RobotLink, optional
        Default: :func:`drivers.factory.open_link` on ``settings.robot.link_url``, or a
        :class:`drivers.link_process.ProcessLink` when ``robot.link_process`` is set (not connected
        until start-up).
    phantom, robot_model : optional
        Pre-loaded :class:`registration.model.phantom.Phantom` /
        :class:`registration.model.kinematics.RobotModel`.

    Raises
    ------
    ConfigError, RobotLinkError
        Bad phantom file, robot model or link URL (fail at start-up, naming the setting).
    """
    settings.check_serving()
    phantom = phantom if phantom is not None else load_phantom(settings)
    settings.check_robot_side(phantom.size_mm)
    return ServiceInputs(
        settings=settings,
        bus=EventBus(),
        phantom=phantom,
        robot_model=robot_model if robot_model is not None else load_robot_model(settings),
        robot_link=robot_link if robot_link is not None else open_link(settings),
    )


def load_phantom(settings: Settings) -> Phantom:
    from registration.model.phantom import load_phantom

    return load_phantom(settings.phantom_file)


def load_robot_model(settings: Settings) -> RobotModel:
    from registration.errors import ConfigError

    try:
        return RobotModel.load(settings.robot.model)
    except ConfigError as e:
        raise ConfigError(f"setting 'robot.model' ({settings.robot.model!r}): {e}") from None


def open_link(settings: Settings) -> RobotLink:
    from drivers.factory import open_link
    from drivers.link_process import ProcessLink

    if settings.robot.link_process:  # the reader in a child process, out of the GIL's reach
        return ProcessLink(settings.robot.link_url)
    return open_link(settings.robot.link_url)
