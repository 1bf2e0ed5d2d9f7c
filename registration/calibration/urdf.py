"""A serial arm as a numpy chain read from its URDF, and the calibrated-URDF writer.

The chain is the URDF's own description, joint by joint from the root link
``base`` to the frame ``tool0``::

    robot_from_tool0(q) = M_1 · Rot(a_1, q_1) · M_2 · Rot(a_2, q_2) · … · M_6 · Rot(a_6, q_6) · M_tool

``M_i`` is joint *i*'s ``<origin>`` (in its parent link, mm here), ``a_i`` its
``<axis>``; fixed joints between two actuated ones are folded into the next
``M``.  This is the same product Pinocchio evaluates for the URDF (checked to
1e-9 mm in ``tests/unit/registration/calibration/test_calibration_urdf.py``), written in numpy so that
the calibration can evaluate it for many poses and perturbed origins at once.

:func:`write_calibrated_urdf` writes a copy of the nominal URDF with corrected
``<origin>`` elements (same links, joints, limits and comments, plus one
comment naming the calibration); :meth:`RobotModel.load
<registration.model.kinematics.RobotModel.load>` reads it like any other URDF.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Final

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from registration.arrays import F64
from registration.errors import ConfigError, KinematicsError
from registration.model.frames import transform_from_xyz_rpy

MM_PER_M: Final = 1000.0
ROOT_LINK: Final = "base"
TOOL_LINK: Final = "tool0"


def rotation_about(axis: F64, angles_rad: F64) -> F64:
    """Rodrigues rotations about one unit ``axis`` (3,) by ``angles_rad`` (K,) → (K, 3, 3)."""
    a = np.asarray(angles_rad, dtype=np.float64).reshape(-1)
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    s = np.sin(a)[:, None, None]
    c = np.cos(a)[:, None, None]
    return np.asarray(np.eye(3) + s * k + (1.0 - c) * (k @ k), dtype=np.float64)


@dataclass(frozen=True, eq=False)
class SerialChain:
    """A serial revolute arm: ``M_i`` (n, 4, 4) mm, axes ``a_i`` (n, 3), ``M_tool`` (4, 4) mm.

    Attributes
    ----------
    joint_names : tuple of str
        Actuated joints in configuration order.
    parent_from_joint : ndarray, shape (n, 4, 4), float64
        ``M_i``: joint *i*'s frame (at q_i = 0) in the previous joint's frame
        (the root link ``base`` for joint 1), mm.
    axes : ndarray, shape (n, 3), float64
        Unit rotation axis of each joint in its own frame.
    last_from_tool0 : ndarray, shape (4, 4), float64
        ``tool0`` in the last joint's frame, mm.
    lower_rad, upper_rad : ndarray, shape (n,)
        Joint limits from the URDF.
    urdf_path : Path
        The URDF the chain was read from (the template of the writer).
    """

    joint_names: tuple[str, ...]
    parent_from_joint: F64
    axes: F64
    last_from_tool0: F64
    lower_rad: F64
    upper_rad: F64
    urdf_path: Path

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    def robot_from_tool0_batch(self, joints_rad: ArrayLike) -> F64:
        """``robot_from_tool0`` (K, 4, 4) mm for joint angles (K, n) rad (no limit check)."""
        q = np.asarray(joints_rad, dtype=np.float64)
        q = q.reshape(-1, self.n_joints)
        out = np.broadcast_to(np.eye(4), (len(q), 4, 4)).copy()
        for i in range(self.n_joints):
            out = out @ self.parent_from_joint[i]
            rot = rotation_about(self.axes[i], q[:, i])
            out[:, :3, :3] = out[:, :3, :3] @ rot
        return np.asarray(out @ self.last_from_tool0, dtype=np.float64)

    def robot_from_tool0(self, joints_rad: ArrayLike) -> F64:
        """``robot_from_tool0`` (4, 4) mm at one joint vector (rad), limits checked."""
        q = np.asarray(joints_rad, dtype=np.float64).reshape(-1)
        if q.size != self.n_joints or not np.all(np.isfinite(q)):
            raise KinematicsError(f"expected {self.n_joints} finite joint values, got {q.tolist()}")
        return np.asarray(self.robot_from_tool0_batch(q[None, :])[0], dtype=np.float64)

    def with_origins(
        self, parent_from_joint: ArrayLike, last_from_tool0: ArrayLike | None = None
    ) -> SerialChain:
        """The same chain with other joint origins (mm) and optionally another tool0 placement."""
        m = np.asarray(parent_from_joint, dtype=np.float64).reshape(self.n_joints, 4, 4)
        tool = (
            self.last_from_tool0 if last_from_tool0 is None else np.asarray(last_from_tool0, dtype=np.float64)
        )
        return replace(self, parent_from_joint=m.copy(), last_from_tool0=tool.copy())


def _origin_mm(joint: ET.Element) -> F64:
    org = joint.find("origin")
    xyz = [0.0, 0.0, 0.0] if org is None else [float(v) for v in org.get("xyz", "0 0 0").split()]
    rpy = [0.0, 0.0, 0.0] if org is None else [float(v) for v in org.get("rpy", "0 0 0").split()]
    return transform_from_xyz_rpy(np.asarray(xyz) * MM_PER_M, np.degrees(rpy))


def _chain_joints(root: ET.Element, path: Path) -> list[ET.Element]:
    """The joints from ``base`` to ``tool0`` in order (ConfigError if the path is missing)."""
    by_child: dict[str, ET.Element] = {}
    for j in root.iter("joint"):
        child = j.find("child")
        if child is not None:
            by_child[child.get("link", "")] = j
    chain: list[ET.Element] = []
    link = TOOL_LINK
    while link != ROOT_LINK:
        found = by_child.get(link)
        if found is None:
            raise ConfigError(
                f"robot URDF {path}: no joint chain from {ROOT_LINK!r} to {TOOL_LINK!r} ({link!r})"
            )
        chain.append(found)
        if len(chain) > len(by_child):
            raise ConfigError(f"robot URDF {path}: the joints form a loop above {link!r}")
        parent = found.find("parent")
        link = "" if parent is None else parent.get("link", "")
    return chain[::-1]


def read_chain(urdf_path: str | Path) -> SerialChain:
    """Read the ``base`` → ``tool0`` chain of a URDF (revolute and fixed joints only).

    Raises
    ------
    ConfigError
        File missing or unparsable, no chain from ``base`` to ``tool0``, or a
        joint type other than revolute / fixed.
    """
    path = Path(urdf_path)
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as e:
        raise ConfigError(f"cannot read robot URDF {path}: {e}") from None
    names: list[str] = []
    placements: list[F64] = []
    axes: list[F64] = []
    lower: list[float] = []
    upper: list[float] = []
    pending = np.eye(4)
    for j in _chain_joints(root, path):
        kind = j.get("type", "")
        pending = pending @ _origin_mm(j)
        if kind == "fixed":
            continue
        if kind != "revolute":
            raise ConfigError(
                f"robot URDF {path}: joint {j.get('name')!r} is {kind!r}; only revolute supported"
            )
        ax_el = j.find("axis")
        axis = (
            np.array([1.0, 0.0, 0.0])
            if ax_el is None
            else np.array([float(v) for v in ax_el.get("xyz", "1 0 0").split()])
        )
        lim = j.find("limit")
        names.append(str(j.get("name")))
        placements.append(pending)
        axes.append(axis / np.linalg.norm(axis))
        lower.append(float(lim.get("lower", "0")) if lim is not None else -np.pi)
        upper.append(float(lim.get("upper", "0")) if lim is not None else np.pi)
        pending = np.eye(4)
    return SerialChain(
        joint_names=tuple(names),
        parent_from_joint=np.stack(placements),
        axes=np.stack(axes),
        last_from_tool0=pending,
        lower_rad=np.array(lower),
        upper_rad=np.array(upper),
        urdf_path=path,
    )


def _fmt(v: float) -> str:
    return repr(float(v))


def write_calibrated_urdf(chain: SerialChain, out_path: str | Path, *, comment: str) -> Path:
    """Write ``chain``'s joint origins into a copy of its template URDF.

    The template (``chain.urdf_path``) must have no fixed joint between two
    actuated joints other than after the last one (true of the project's
    TX60 / TX2-60 URDFs): each actuated joint's ``<origin>`` receives its
    ``M_i``, the fixed joint(s) after the last actuated joint keep their
    nominal origins except the last one, which receives ``M_tool`` composed
    with the inverse of the preceding fixed origins.  Links, joint names, axes,
    limits and comments are kept; ``comment`` is added at the top of the robot.

    Returns
    -------
    Path
        ``out_path``.

    Raises
    ------
    ConfigError
        The template has fixed joints inside the actuated chain.
    """
    path = Path(chain.urdf_path)
    parser = ET.XMLParser(target=ET.TreeBuilder(insert_comments=True))
    tree = ET.parse(path, parser)
    root = tree.getroot()
    joints = _chain_joints(root, path)
    actuated = [j for j in joints if j.get("type") != "fixed"]
    first = joints.index(actuated[0])
    last = joints.index(actuated[-1])
    if any(j.get("type") == "fixed" for j in joints[first : last + 1]):
        raise ConfigError(f"{path}: fixed joints between actuated joints are not supported by the writer")
    if first > 0:  # fixed joints before joint 1: fold their origins into M_1
        pre = np.eye(4)
        for j in joints[:first]:
            pre = pre @ _origin_mm(j)
        m = chain.parent_from_joint.copy()
        m[0] = np.linalg.inv(pre) @ m[0]
    else:
        m = chain.parent_from_joint
    for j, mi in zip(actuated, m, strict=True):
        _set_origin(j, mi)
    tail = joints[last + 1 :]
    if tail:
        pre = np.eye(4)
        for j in tail[:-1]:
            pre = pre @ _origin_mm(j)
        _set_origin(tail[-1], np.linalg.inv(pre) @ chain.last_from_tool0)
    note = ET.Comment(" " + comment.replace("--", "- -") + " ")
    note.tail = "\n  "
    root.insert(0, note)
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    tree.write(out, encoding="utf-8", xml_declaration=True)
    return out


def _set_origin(joint: ET.Element, parent_from_joint_mm: F64) -> None:
    org = joint.find("origin")
    if org is None:
        org = ET.SubElement(joint, "origin")
    xyz_m = parent_from_joint_mm[:3, 3] / MM_PER_M
    rpy = Rotation.from_matrix(parent_from_joint_mm[:3, :3]).as_euler("xyz")
    org.set("xyz", " ".join(_fmt(v) for v in xyz_m))
    org.set("rpy", " ".join(_fmt(v) for v in rpy))
