"""One simulated O-arm placement, named: the scans ``oarmreg simulate --joints --placement NAME``
writes share a hidden ``image_from_robot`` and a FrameOfReferenceUID, both derived from the name
alone, so separate ``simulate`` runs make one calibration session as one real O-arm placement does.

The robot side goes through :class:`mocks.cell.TrueCell` (seeded): the phantom is posed where the
*true* arm puts it, the joints written beside the scan are what the controller would report
(encoder noise included), so the scans carry kinematic error like a real arm's.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from mocks.cell import SPREAD_BASE_JOINTS_RAD, TrueCell
from mocks.oarm.simulator import demo_pose
from registration.arrays import F64
from registration.model.frames import invert, transform_from_xyz_rpy
from registration.model.kinematics import RobotModel, default_tool0_from_phantom

DEFAULT_CELL_SEED = 2
"""Seed of the simulated true cell (:meth:`mocks.cell.TrueCell.sample`), the demo's own."""
PLACEMENT_SHIFT_MM = 8.0
"""Largest offset per axis of a placement from the reference one (mm): an O-arm rolled back into
roughly the same spot; small enough for the phantom to stay inside the small presets' volume."""
PLACEMENT_TILT_DEG = 3.0
"""Largest rotation per axis of a placement from the reference one (deg)."""
UUID_DERIVED_UID_ROOT = "2.25."
"""DICOM PS3.5 §B.2: a UID made of ``2.25.`` and a 128-bit number in decimal."""


def placement_frame_of_reference_uid(name: str) -> str:
    """The FrameOfReferenceUID of placement ``name``: ``2.25.`` + 128 bits of SHA-256 of the name
    (the same name gives the same UID in every run; ≤ 44 characters)."""
    digest = hashlib.sha256(f"oarmreg-placement:{name}".encode()).digest()
    return UUID_DERIVED_UID_ROOT + str(int.from_bytes(digest[:16], "big"))


def _placement_offset(name: str) -> F64:
    """A deterministic small rigid motion of the O-arm for ``name`` (4 × 4, mm)."""
    seed = int.from_bytes(hashlib.sha256(f"oarmreg-placement-pose:{name}".encode()).digest()[:8], "big")
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(-PLACEMENT_SHIFT_MM, PLACEMENT_SHIFT_MM, 3)
    rpy = rng.uniform(-PLACEMENT_TILT_DEG, PLACEMENT_TILT_DEG, 3)
    return transform_from_xyz_rpy(xyz, rpy)


@dataclass(frozen=True, eq=False)
class Placement:
    """A named O-arm placement beside a simulated true cell."""

    name: str
    cell: TrueCell
    image_from_robot: F64
    frame_of_reference_uid: str

    def image_from_phantom_true(self, joints_rad: ArrayLike, rng: np.random.Generator | None = None) -> F64:
        """Where the phantom really is in the image when the arm is commanded to ``joints_rad``."""
        return self.cell.image_from_phantom_true(self.image_from_robot, joints_rad, rng)


def make_placement(name: str, robot: str = "tx60", cell_seed: int = DEFAULT_CELL_SEED) -> Placement:
    """Placement ``name``: the reference placement (the phantom at the simulator's demo pose when
    the arm is at :data:`mocks.cell.SPREAD_BASE_JOINTS_RAD`) moved by a small motion drawn from the
    name."""
    if not name.strip():
        raise ValueError("the placement name must not be empty")
    model = RobotModel.load(robot)
    cell = TrueCell.sample(cell_seed, model, default_tool0_from_phantom())
    reference = demo_pose() @ invert(
        cell.robot_from_tool0_true(SPREAD_BASE_JOINTS_RAD) @ cell.tool0_from_phantom
    )
    return Placement(
        name=name,
        cell=cell,
        image_from_robot=np.asarray(_placement_offset(name) @ reference, dtype=np.float64),
        frame_of_reference_uid=placement_frame_of_reference_uid(name),
    )


def reported_joints(placement: Placement, joints_rad: ArrayLike, rng: np.random.Generator) -> list[float]:
    """The joints the controller reports at ``joints_rad`` (with the cell's encoder noise)."""
    return [float(v) for v in placement.cell.reported_joints(joints_rad, rng)]
