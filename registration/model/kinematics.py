"""Forward kinematics of the Stäubli arm (Pinocchio) and sphere centres in the robot frame.

The paper obtains the sphere positions in robot space "by the kinematics of the
robot" (Bai et al. 2018, doi:10.1088/1742-6596/1016/1/012006, §2.3):

    centres_robot = robot_from_tool0(q) @ tool0_from_phantom @ centres_phantom

``robot`` is the Stäubli world frame (the URDF root link ``base``), ``tool0``
the flange frame (z out of the flange).  The project's URDFs live in
``configs/robots/`` (see the README there).  Pinocchio works in metres; this
module converts to millimetres in exactly one place, :func:`_placement_to_mm`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from registration.arrays import F64
from registration.errors import ConfigError, KinematicsError
from registration.io.resources import robot_urdf, robots_dir
from registration.model.frames import apply, as_transform

ROOT_FRAME = "base"
TOOL_FRAME = "tool0"

MM_PER_M = 1000.0

JOINT_LIMIT_TOLERANCE_RAD = 1e-9
"""Slack on the joint limits for float64 round-off (a value exactly at a limit is legal).  A joint read
over a controller link also gets the link's own wire resolution (``resolution_rad``: float32 over
simple_message rounds by up to 2.4e-7 rad at ±270°)."""

DEGREES_HINT_RAD = 2.0 * math.pi
"""A joint value beyond a limit and larger than this in magnitude (rad) reads as degrees sent as radians."""

DEFAULT_TOOL0_FROM_PHANTOM_XYZ_MM = (0.0, 0.0, 200.0)
DEFAULT_TOOL0_FROM_PHANTOM_RPY_DEG = (180.0, 0.0, 0.0)
"""Default connecting rod: phantom centre 200 mm along tool0 +z, phantom +z pointing back at the
flange (the project brief); a real cell measures its own and sets it in config."""


def _placement_to_mm(rotation: Any, translation_m: Any) -> F64:
    """The single metre → millimetre boundary: a Pinocchio placement as a 4 × 4 mm transform."""
    out = np.eye(4)
    out[:3, :3] = np.asarray(rotation, dtype=np.float64)
    out[:3, 3] = np.asarray(translation_m, dtype=np.float64).reshape(3) * MM_PER_M
    return out


@dataclass(frozen=True, eq=False)
class RobotModel:
    """A loaded arm model.  Constant; per-call workspaces are created by each call.

    Attributes
    ----------
    name : str
    urdf_path : Path
    joint_names : tuple of str
        Actuated joints in configuration order (``joint_1`` … ``joint_6``).
    lower_rad, upper_rad : ndarray, shape (n_joints,)
        Joint limits from the URDF.
    """

    name: str
    urdf_path: Path
    joint_names: tuple[str, ...]
    lower_rad: F64
    upper_rad: F64
    _model: Any = field(repr=False)
    _root_frame_id: int = field(repr=False)
    _tool_frame_id: int = field(repr=False)

    @classmethod
    def load(cls, name_or_urdf: str | Path) -> RobotModel:
        """Load ``"tx60"`` / ``"tx2_60"`` (from ``configs/robots``) or a URDF path.

        The URDF must have a ``base`` and a ``tool0`` frame and revolute joints only.

        Raises
        ------
        ConfigError
            Unknown name, missing file, unparsable URDF, or missing frames.
        """
        import pinocchio as pin

        text = str(name_or_urdf)
        path = Path(text)
        if not text.endswith(".urdf"):
            path = robot_urdf(text)
            if not path.is_file():
                known = sorted(p.stem for p in robots_dir().glob("*.urdf"))
                raise ConfigError(f"unknown robot model {text!r}: expected one of {known} or a .urdf path")
        if not path.is_file():
            raise ConfigError(f"robot URDF {path} does not exist")
        try:
            model = pin.buildModelFromUrdf(str(path))
        except (ValueError, RuntimeError) as e:
            raise ConfigError(f"cannot load robot URDF {path}: {e}") from None
        ids = {}
        for frame in (ROOT_FRAME, TOOL_FRAME):
            if not model.existFrame(frame):
                raise ConfigError(
                    f"robot URDF {path} has no frame {frame!r} (needed: {ROOT_FRAME}, {TOOL_FRAME})"
                )
            ids[frame] = model.getFrameId(frame)
        if model.nq != model.nv:
            raise ConfigError(f"robot URDF {path}: only revolute / prismatic joints are supported")
        names = tuple(str(n) for n in list(model.names)[1:])
        return cls(
            name=path.stem,
            urdf_path=path,
            joint_names=names,
            lower_rad=np.array(model.lowerPositionLimit, dtype=np.float64),
            upper_rad=np.array(model.upperPositionLimit, dtype=np.float64),
            _model=model,
            _root_frame_id=ids[ROOT_FRAME],
            _tool_frame_id=ids[TOOL_FRAME],
        )

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    def check_joints(self, joints_rad: ArrayLike, *, resolution_rad: ArrayLike = 0.0) -> F64:
        """Return ``joints_rad`` as float64 (n_joints,) after checking count, NaN and limits.

        A value within ``resolution_rad`` of a limit (the wire encoding's rounding, as the link that
        read it states it; never less than :data:`JOINT_LIMIT_TOLERANCE_RAD`) is at the limit and is
        returned as the limit itself (:meth:`at_limits`).

        Raises
        ------
        KinematicsError
            Wrong count, non-finite value, or a joint beyond its limit by more than the rounding
            (named, with value, limit and excess in degrees, and a hint that says what is likely).
        """
        q = np.asarray(joints_rad, dtype=np.float64).reshape(-1)
        if q.size != self.n_joints:
            raise KinematicsError(
                f"{self.name}: expected {self.n_joints} joint values ({', '.join(self.joint_names)}), "
                f"got {q.size}"
            )
        bad = [self.joint_names[i] for i in range(q.size) if not math.isfinite(q[i])]
        if bad:
            raise KinematicsError(f"{self.name}: joint values must be finite; {', '.join(bad)} = NaN/inf")
        tol = self._tolerance_rad(resolution_rad)
        for i, name in enumerate(self.joint_names):
            lo, hi = self.lower_rad[i], self.upper_rad[i]
            if not lo - tol[i] <= q[i] <= hi + tol[i]:
                raise KinematicsError(
                    self._limit_message(name, float(q[i]), float(lo), float(hi), float(tol[i]))
                )
        return self.at_limits(q, tol)

    def at_limits(self, joints_rad: ArrayLike, resolution_rad: ArrayLike = 0.0) -> F64:
        """``joints_rad`` with every value within ``resolution_rad`` (or :data:`JOINT_LIMIT_TOLERANCE_RAD`)
        of a limit, on either side, put at that limit: the wire cannot tell them from it.  Other values
        are unchanged (one farther beyond stays, for :meth:`check_joints` to refuse)."""
        q = np.asarray(joints_rad, dtype=np.float64).reshape(-1).copy()
        if q.size != self.n_joints:
            return q
        tol = self._tolerance_rad(resolution_rad)
        low = np.abs(q - self.lower_rad) <= tol
        high = np.abs(q - self.upper_rad) <= tol
        q[low], q[high] = self.lower_rad[low], self.upper_rad[high]
        return q

    def _tolerance_rad(self, resolution_rad: ArrayLike) -> F64:
        res = np.broadcast_to(np.asarray(resolution_rad, dtype=np.float64), (self.n_joints,))
        if not np.all(np.isfinite(res) & (res >= 0)):
            raise KinematicsError(f"{self.name}: resolution_rad must be finite and >= 0, got {res.tolist()}")
        return np.maximum(res, JOINT_LIMIT_TOLERANCE_RAD)

    def _limit_message(self, name: str, q: float, lo: float, hi: float, tol: float) -> str:
        excess = q - hi if q > hi else lo - q
        head = (
            f"{self.name}: {name} = {math.degrees(q):.4f}° is outside its limit "
            f"[{math.degrees(lo):.4f}°, {math.degrees(hi):.4f}°] ({self.urdf_path.name}): {q:.9g} rad is "
            f"{math.degrees(excess):.4g}° ({excess:.3g} rad) beyond it, more than the {tol:.2g} rad the "
            "joint's encoding can round; "
        )
        if abs(q) > DEGREES_HINT_RAD and lo <= math.radians(q) <= hi:
            return head + (
                f"{q:.6g} looks like degrees ({math.radians(q):.6g} rad would be inside the limit): "
                "the controller or the file must send radians"
            )
        return head + (
            "the arm cannot stand there: check that the robot model is the arm connected "
            "(robot.model) and that the controller reports the joints with their zero and sign "
            "as the URDF defines them"
        )

    def robot_from_tool0(self, joints_rad: ArrayLike) -> F64:
        """Pose of ``tool0`` in the robot frame (4 × 4, mm) at joint angles ``joints_rad`` (rad).

        Raises
        ------
        KinematicsError
            See :meth:`check_joints`.
        """
        import pinocchio as pin

        q = self.check_joints(joints_rad)
        data = self._model.createData()
        pin.framesForwardKinematics(self._model, data, q)
        base_m = data.oMf[self._root_frame_id]
        tool_m = data.oMf[self._tool_frame_id]
        base_from_tool = base_m.actInv(tool_m)  # base⁻¹ · tool, both in metres
        return _placement_to_mm(base_from_tool.rotation, base_from_tool.translation)


def sphere_centres_robot_mm(
    model: RobotModel, joints_rad: ArrayLike, tool0_from_phantom: ArrayLike, centres_phantom_mm: ArrayLike
) -> F64:
    """Sphere centres in the robot frame.

    Parameters
    ----------
    model : RobotModel
    joints_rad : array_like, shape (n_joints,)
        Joint angles in radians.
    tool0_from_phantom : array_like, shape (4, 4)
        The connecting rod (mm); checked to be rigid.
    centres_phantom_mm : array_like, shape (N, 3)
        Sphere centres in the phantom frame (mm), in phantom sphere order.

    Returns
    -------
    ndarray, shape (N, 3), float64
        Centres in the ``robot`` frame (mm), same order.
    """
    rod = as_transform(tool0_from_phantom, "tool0_from_phantom")
    pts = np.asarray(centres_phantom_mm, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise KinematicsError(f"centres_phantom_mm must have shape (N, 3), got {pts.shape}")
    robot_from_phantom = model.robot_from_tool0(joints_rad) @ rod
    return apply(robot_from_phantom, pts)


def default_tool0_from_phantom() -> F64:
    """The brief's default connecting rod (see :data:`DEFAULT_TOOL0_FROM_PHANTOM_XYZ_MM`)."""
    from registration.model.frames import transform_from_xyz_rpy

    return transform_from_xyz_rpy(DEFAULT_TOOL0_FROM_PHANTOM_XYZ_MM, DEFAULT_TOOL0_FROM_PHANTOM_RPY_DEG)
