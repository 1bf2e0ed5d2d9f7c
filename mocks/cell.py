"""The cell the simulator poses the phantom with: exact (nominal) or true (design.md §8).

A :class:`TrueCell` is a seeded draw of how a real cell differs from its
catalogue description:

* every joint origin of the URDF (``M_i``, also the base and flange) is off by
  a small rigid motion (translation σ per axis in mm, rotation σ per axis),
* every joint has a zero offset (the encoder reads q while the joint is at
  q + offset),
* a gravity-like deflection of J2 and J3 that depends on the arm's posture
  (∝ sin of the link angle from the vertical) — no geometric model has it,
* the connecting rod (``tool0_from_phantom``) is off by a fixed distance and
  angle in random directions,
* each move lands within a repeatability (a random tool0 translation per pose),
* the reported joints carry encoder noise.

Defaults (:class:`CellErrorSizes`) are the error sizes the project specifies for the cell, after
the TX60 study quoted in ``research/calibration.md`` §1 (0.31 mm mean nominal error).
:class:`ExactCell` has the same interface with nominal everything and no noise.
Both take the simulator's ``image_from_robot`` and return the
``image_from_phantom`` to pass to :func:`mocks.oarm.simulator.simulate_scan`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike

from registration.arrays import F64
from registration.calibration.urdf import SerialChain, read_chain, rotation_about
from registration.model.frames import as_transform, make_transform
from registration.model.kinematics import RobotModel

SPREAD_BASE_JOINTS_RAD = np.array([0.2, 0.3, 1.6, 0.1, 0.8, -0.3])
"""A TX60 configuration inside every joint's limits, the centre of the spread poses (rad)."""

SPREAD_OFFSETS_RAD = np.array(
    [
        [0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        [1.2, -0.6, 0.4, 1.4, -0.9, 2.0],
        [-1.1, 0.7, -0.8, -1.3, 0.6, -1.8],
        [0.6, 1.0, -1.2, 2.2, 0.9, 0.5],
        [-0.5, -1.0, 0.9, -2.1, -1.2, -0.7],
        [1.4, 0.4, 0.7, -0.6, 1.3, 1.2],
        [-1.4, -0.3, -0.5, 0.7, -1.4, -1.3],
        [0.3, 1.2, 0.2, -1.5, 0.3, 2.6],
        [-0.2, -1.2, -1.3, 1.6, -0.4, -2.4],
        [0.9, -0.9, 1.1, 0.3, 1.1, -0.2],
        [-0.8, 0.9, -0.2, -0.4, -0.8, 1.7],
        [0.1, 0.2, -1.0, 1.0, 1.4, -1.0],
    ]
)
"""Twelve hand-picked offsets from :data:`SPREAD_BASE_JOINTS_RAD` (rad) spreading every joint by
≥ ± 1 rad: a well-conditioned set for the 18-parameter robot calibration."""

SPREAD_JOINTS_RAD = SPREAD_BASE_JOINTS_RAD + SPREAD_OFFSETS_RAD[:10]
"""Ten TX60 poses spread over every joint (rad), for synthetic calibration sessions in tests and
benchmarks: well conditioned for the 18-parameter robot set."""


@dataclass(frozen=True)
class CellErrorSizes:
    """Sizes of the true cell's deviations from nominal (units in the names)."""

    joint_origin_translation_mm: float = 0.12
    """σ per axis of every joint origin's translation error."""
    joint_origin_rotation_deg: float = 0.012
    """σ per axis of every joint origin's rotation error."""
    joint_zero_offset_deg: float = 0.012
    """σ of every joint's zero offset."""
    rod_translation_mm: float = 0.8
    """Length of the rod's translation error (random direction)."""
    rod_rotation_deg: float = 0.4
    """Angle of the rod's rotation error (random axis)."""
    sag_j2j3_rms_deg: float = 0.003
    """RMS over postures of the J2 / J3 gravity deflection."""
    repeatability_mm: float = 0.02
    """RMS length of the per-move tool0 translation scatter."""
    encoder_noise_rad: float = 1e-5
    """σ of the reported joint angles around the real ones."""


def _small_motion(rng: np.random.Generator, translation_sd_mm: float, rotation_sd_deg: float) -> F64:
    w = rng.normal(0.0, math.radians(rotation_sd_deg), 3)
    ang = float(np.linalg.norm(w))
    axis = w / ang if ang > 0 else np.array([0.0, 0.0, 1.0])
    return make_transform(rotation_about(axis, np.array([ang]))[0], rng.normal(0.0, translation_sd_mm, 3))


def _fixed_size_motion(rng: np.random.Generator, translation_mm: float, rotation_deg: float) -> F64:
    d = rng.normal(size=3)
    axis = rng.normal(size=3)
    rot = rotation_about(axis / np.linalg.norm(axis), np.array([math.radians(rotation_deg)]))[0]
    return make_transform(rot, translation_mm * d / np.linalg.norm(d))


class Cell(Protocol):
    """What the simulator needs from a cell."""

    @property
    def tool0_from_phantom(self) -> F64: ...

    def robot_from_tool0_true(self, joints_rad: ArrayLike, rng: np.random.Generator | None = None) -> F64: ...

    def reported_joints(self, joints_rad: ArrayLike, rng: np.random.Generator | None = None) -> F64: ...

    def image_from_phantom_true(
        self, image_from_robot: ArrayLike, joints_rad: ArrayLike, rng: np.random.Generator | None = None
    ) -> F64: ...


@dataclass(frozen=True, eq=False)
class TrueCell:
    """A robot + rod that differ from the nominal ones (see the module docstring).

    Attributes
    ----------
    chain : SerialChain
        The true geometry (origins with errors; offsets not included).
    joint_offsets_rad : ndarray, shape (n,)
        Zero offsets: a joint read (and commanded) as q is really at q + offset.
    tool0_from_phantom : ndarray, shape (4, 4)
        The true rod (mm).
    sizes : CellErrorSizes
    sag_gain_rad : float
        Amplitude of the J2 / J3 deflection.
    """

    chain: SerialChain
    joint_offsets_rad: F64
    tool0_from_phantom: F64
    sizes: CellErrorSizes
    sag_gain_rad: float

    @classmethod
    def sample(
        cls,
        seed: int,
        nominal_model: RobotModel,
        nominal_tool0_from_phantom: ArrayLike,
        sizes: CellErrorSizes = CellErrorSizes(),
    ) -> TrueCell:
        """Draw a true cell around ``nominal_model`` and the nominal rod (deterministic in ``seed``)."""
        rng = np.random.default_rng(seed)
        nominal = read_chain(nominal_model.urdf_path)
        origins = np.stack(
            [
                m @ _small_motion(rng, sizes.joint_origin_translation_mm, sizes.joint_origin_rotation_deg)
                for m in nominal.parent_from_joint
            ]
        )
        tool = nominal.last_from_tool0 @ _small_motion(
            rng, sizes.joint_origin_translation_mm, sizes.joint_origin_rotation_deg
        )
        offsets = rng.normal(0.0, math.radians(sizes.joint_zero_offset_deg), nominal.n_joints)
        rod = as_transform(nominal_tool0_from_phantom, "nominal_tool0_from_phantom") @ _fixed_size_motion(
            rng, sizes.rod_translation_mm, sizes.rod_rotation_deg
        )
        # sin(θ) of a uniformly spread posture angle has RMS 1/√2: gain = √2 × RMS
        gain = math.sqrt(2.0) * math.radians(sizes.sag_j2j3_rms_deg)
        return cls(nominal.with_origins(origins, tool), offsets, rod, sizes, gain)

    def sag_rad(self, joints_rad: ArrayLike) -> F64:
        """The J2 / J3 deflection (n,) rad at ``joints_rad``: gravity torque ∝ sin of the link angles.

        q = 0 is the arm straight up (TX60 URDF), so the upper arm's lever is
        sin q2 and the forearm's sin(q2 + q3).
        """
        q = np.asarray(joints_rad, dtype=np.float64).reshape(-1)
        out = np.zeros_like(q)
        out[1] = self.sag_gain_rad * (math.sin(q[1]) + 0.5 * math.sin(q[1] + q[2])) / 1.25
        out[2] = self.sag_gain_rad * math.sin(q[1] + q[2])
        return out

    def robot_from_tool0_true(self, joints_rad: ArrayLike, rng: np.random.Generator | None = None) -> F64:
        """Where tool0 really is (4 × 4 mm) when the joints are at ``joints_rad`` (rad).

        With ``rng``, one draw of the repeatability scatter is added (one move).
        """
        q = np.asarray(joints_rad, dtype=np.float64).reshape(-1)
        real = q + self.joint_offsets_rad + self.sag_rad(q)
        t = self.chain.robot_from_tool0_batch(real[None, :])[0]
        if rng is not None and self.sizes.repeatability_mm > 0:
            t = t.copy()
            t[:3, 3] += rng.normal(0.0, self.sizes.repeatability_mm / math.sqrt(3.0), 3)
        return np.asarray(t, dtype=np.float64)

    def reported_joints(self, joints_rad: ArrayLike, rng: np.random.Generator | None = None) -> F64:
        """What the controller reports at ``joints_rad``: + encoder noise when ``rng`` is given."""
        q = np.asarray(joints_rad, dtype=np.float64).reshape(-1).copy()
        if rng is not None:
            q += rng.normal(0.0, self.sizes.encoder_noise_rad, q.shape)
        return q

    def image_from_phantom_true(
        self, image_from_robot: ArrayLike, joints_rad: ArrayLike, rng: np.random.Generator | None = None
    ) -> F64:
        """The phantom's real pose in the image for the simulator (4 × 4 mm)."""
        y = as_transform(image_from_robot, "image_from_robot")
        return np.asarray(
            y @ self.robot_from_tool0_true(joints_rad, rng) @ self.tool0_from_phantom, dtype=np.float64
        )


@dataclass(frozen=True, eq=False)
class ExactCell:
    """The nominal cell: the robot moves exactly as its URDF says, the rod is as drawn, no noise."""

    chain: SerialChain
    tool0_from_phantom: F64

    @classmethod
    def sample(
        cls,
        seed: int,
        nominal_model: RobotModel,
        nominal_tool0_from_phantom: ArrayLike,
        sizes: CellErrorSizes = CellErrorSizes(),
    ) -> ExactCell:
        """Same signature as :meth:`TrueCell.sample`; ``seed`` and ``sizes`` are ignored."""
        rod = as_transform(nominal_tool0_from_phantom, "nominal_tool0_from_phantom")
        return cls(read_chain(nominal_model.urdf_path), rod.copy())

    def robot_from_tool0_true(self, joints_rad: ArrayLike, rng: np.random.Generator | None = None) -> F64:
        return self.chain.robot_from_tool0(joints_rad)

    def reported_joints(self, joints_rad: ArrayLike, rng: np.random.Generator | None = None) -> F64:
        return np.asarray(joints_rad, dtype=np.float64).reshape(-1).copy()

    def image_from_phantom_true(
        self, image_from_robot: ArrayLike, joints_rad: ArrayLike, rng: np.random.Generator | None = None
    ) -> F64:
        y = as_transform(image_from_robot, "image_from_robot")
        return np.asarray(
            y @ self.robot_from_tool0_true(joints_rad) @ self.tool0_from_phantom, dtype=np.float64
        )


# ---------------------------------------------------------------- a simulated calibration session


@dataclass(frozen=True, eq=False)
class SimulatedPose:
    """One simulated scan of a session: what the service would see, and the truth behind it."""

    name: str
    joints_reported_rad: F64
    detections_image_mm: F64
    truth_image_from_phantom: F64
    series_uid: str
    frame_of_reference_uid: str
    detect_s: float


def simulate_pose_scan(
    cell: Cell,
    image_from_robot: ArrayLike,
    joints_rad: ArrayLike,
    phantom: Any,
    settings: Any,
    out_dir: Path,
    rng: np.random.Generator,
    *,
    frame_of_reference_uid: str,
    name: str = "",
) -> SimulatedPose:
    """Pose the phantom through ``cell``, simulate the scan, write + reload it as DICOM, detect.

    Returns the reported (noisy) joints, the detections and the true ``image_from_phantom``.
    """
    from mocks.oarm.dicom_export import write_dicom_series
    from mocks.oarm.simulator import simulate_scan
    from registration.detection import detect_spheres, params_for_spheres
    from registration.dicom import load_series

    truth = cell.image_from_phantom_true(image_from_robot, joints_rad, rng)
    reported = cell.reported_joints(joints_rad, rng)
    scan = simulate_scan(phantom, truth, settings)
    export = write_dicom_series(
        scan, out_dir, write_truth=False, frame_of_reference_uid=frame_of_reference_uid
    )
    t0 = time.perf_counter()
    volume = load_series(out_dir)
    # the estimator and size the service chooses for this phantom
    det = detect_spheres(volume, params_for_spheres(phantom.sphere_material, phantom.sphere_diameter_mm))
    return SimulatedPose(
        name=name or out_dir.name,
        joints_reported_rad=reported,
        detections_image_mm=det.centres_image_mm,
        truth_image_from_phantom=truth,
        series_uid=export.series_uid,
        frame_of_reference_uid=volume.frame_of_reference_uid,
        detect_s=time.perf_counter() - t0,
    )
