"""Keep-out report and short-travel ordering for planned calibration poses.

The planner keeps the phantom inside the scan volume; it knows nothing of the O-arm's gantry or
the table.  What it can be told is a **keep-out volume**: axis-aligned boxes in the image frame
(LPS mm) where no part of the arm may go (the gantry's housing beside the bore, the table top
below the volume).  :func:`keep_out_report` says, per pose, how close the arm's joint frames,
tool0 and the phantom centre come to those boxes, and names the poses nearer than a margin.
:func:`order_for_short_travel` reorders the poses so that the largest joint move between
consecutive scans stays small (greedy nearest neighbour from the start joints, by the largest
joint step, then 2-opt).  The geometry is points against boxes: the arm's links are not modelled
as volumes, hence the margin; a report, never a guarantee of no collision.  Pure: numpy only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from registration.arrays import F64
from registration.calibration.urdf import SerialChain, rotation_about
from registration.model.frames import apply, as_transform

NEAR_MARGIN_MM = 50.0
"""A pose is reported "near" a keep-out box when a checked point comes this close (mm): the
points are joint-frame origins, the links around them are ~60-80 mm thick on a TX60."""


@dataclass(frozen=True)
class KeepOutBox:
    """An axis-aligned box in the image frame (LPS mm) the arm must stay out of."""

    name: str
    min_mm: tuple[float, float, float]
    max_mm: tuple[float, float, float]

    def __post_init__(self) -> None:
        lo, hi = np.asarray(self.min_mm, float), np.asarray(self.max_mm, float)
        if lo.shape != (3,) or hi.shape != (3,) or not np.all(np.isfinite(lo) & np.isfinite(hi)):
            raise ValueError(f"keep-out box {self.name!r}: min_mm and max_mm need 3 finite numbers each")
        if np.any(lo >= hi):
            raise ValueError(f"keep-out box {self.name!r}: min_mm must be below max_mm on every axis")

    def signed_distance_mm(self, points_mm: ArrayLike) -> F64:
        """Distance from each point to the box (mm); negative inside (depth below the nearest face)."""
        p = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        lo, hi = np.asarray(self.min_mm), np.asarray(self.max_mm)
        outside = np.maximum(np.maximum(lo - p, p - hi), 0.0)
        inside_depth = np.minimum(p - lo, hi - p).min(axis=1)
        dist = np.where(np.any(outside > 0, axis=1), np.linalg.norm(outside, axis=1), -inside_depth)
        return np.asarray(dist, dtype=np.float64)


@dataclass(frozen=True)
class PoseClearance:
    """One pose: the smallest distance of a checked point to any box, which box and which point."""

    index: int
    clearance_mm: float
    box: str
    point: str
    near: bool


def checked_points_robot_mm(
    chain: SerialChain, joints_rad: ArrayLike, tool0_from_phantom: ArrayLike
) -> tuple[list[str], F64]:
    """Names and robot-frame positions (mm) of every joint frame's origin, tool0 and the phantom."""
    q = np.asarray(joints_rad, dtype=np.float64).reshape(-1)
    t = np.eye(4)
    names, points = [], []
    for i in range(chain.n_joints):
        t = t @ chain.parent_from_joint[i]
        names.append(chain.joint_names[i])
        points.append(t[:3, 3].copy())
        t[:3, :3] = t[:3, :3] @ rotation_about(chain.axes[i], np.array([q[i]]))[0]
    tool0 = t @ chain.last_from_tool0
    phantom = tool0 @ as_transform(tool0_from_phantom, "tool0_from_phantom")
    names += ["tool0", "phantom"]
    points += [tool0[:3, 3], phantom[:3, 3]]
    return names, np.asarray(points, dtype=np.float64)


def keep_out_report(
    image_from_robot: ArrayLike,
    chain: SerialChain,
    tool0_from_phantom: ArrayLike,
    joints_rad: ArrayLike,
    boxes: list[KeepOutBox],
    near_margin_mm: float = NEAR_MARGIN_MM,
) -> list[PoseClearance]:
    """Per pose (rows of ``joints_rad``), its clearance to the keep-out boxes (none: empty list)."""
    if not boxes:
        return []
    y = as_transform(image_from_robot, "image_from_robot")
    out = []
    for k, q in enumerate(np.asarray(joints_rad, dtype=np.float64).reshape(-1, chain.n_joints)):
        names, pts = checked_points_robot_mm(chain, q, tool0_from_phantom)
        img = apply(y, pts)
        best = (np.inf, "", "")
        for box in boxes:
            d = box.signed_distance_mm(img)
            j = int(np.argmin(d))
            if d[j] < best[0]:
                best = (float(d[j]), box.name, names[j])
        out.append(PoseClearance(k, best[0], best[1], best[2], best[0] < near_margin_mm))
    return out


def _max_step(a: F64, b: F64) -> float:
    return float(np.max(np.abs(a - b)))


def travel_rad(start_rad: ArrayLike, joints_rad: ArrayLike, order: list[int]) -> float:
    """Sum over the moves (start → first → … → last) of the largest joint step (rad)."""
    q = np.asarray(joints_rad, dtype=np.float64)
    path = [np.asarray(start_rad, dtype=np.float64).reshape(-1), *(q[i] for i in order)]
    return sum(_max_step(path[i], path[i + 1]) for i in range(len(path) - 1))


def order_for_short_travel(start_rad: ArrayLike, joints_rad: ArrayLike) -> list[int]:
    """An order of the poses with a short total travel from ``start_rad`` (largest joint step per
    move: every joint moves at once, the slowest sets the time): nearest neighbour, then 2-opt
    reversals while one shortens it.  Never longer than the given order."""
    q = np.asarray(joints_rad, dtype=np.float64).reshape(len(np.atleast_2d(joints_rad)), -1)
    n = len(q)
    cur = np.asarray(start_rad, dtype=np.float64).reshape(-1)
    left, order = set(range(n)), []
    while left:
        nxt = min(sorted(left), key=lambda i: _max_step(cur, q[i]))
        order.append(nxt)
        left.remove(nxt)
        cur = q[nxt]
    improved = True
    while improved:
        improved = False
        for i in range(n - 1):
            for j in range(i + 1, n):
                cand = order[:i] + order[i : j + 1][::-1] + order[j + 1 :]
                if travel_rad(start_rad, q, cand) < travel_rad(start_rad, q, order) - 1e-12:
                    order, improved = cand, True
    identity = list(range(n))
    return order if travel_rad(start_rad, q, order) <= travel_rad(start_rad, q, identity) else identity
