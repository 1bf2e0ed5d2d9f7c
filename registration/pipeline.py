"""From a loaded scan and the joints at its acquisition to a registration: pure, no I/O.

:func:`register_scan` runs detection (:func:`registration.detection.detect_spheres`), puts the
phantom's sphere centres into the robot frame through the kinematics
(:func:`registration.model.kinematics.sphere_centres_robot_mm`), registers the two point sets
(:func:`registration.matching.register.register_points`, Bai et al. 2018,
doi:10.1088/1742-6596/1016/1/012006) and predicts the TRE (Fitzpatrick 1998 eq. 46) at targets
given in the image frame.  :func:`verify_scan` is the paper's error analysis (§3, eq. 10) of a
second scan against an existing ``image_from_robot``.

Frames and units: ``image`` = DICOM patient (LPS) mm of the scan, ``robot`` = the robot base,
``tool0`` = the flange, ``phantom`` = the phantom's CAD frame; joints in radians.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from registration.arrays import F64
from registration.detection import DetectionParams, DetectionResult, detect_spheres
from registration.imaging.volume import Volume
from registration.matching.quality import predicted_tre_mm
from registration.matching.records import (
    RegistrationParams,
    RegistrationResult,
)
from registration.matching.register import (
    register_points,
)
from registration.matching.verification import VerificationResult, verify_registration
from registration.model.frames import apply, invert
from registration.model.kinematics import RobotModel, sphere_centres_robot_mm
from registration.model.phantom import Phantom


@dataclass(frozen=True)
class PipelineParams:
    """Settings of one pipeline run.

    Attributes
    ----------
    detection, registration
        Passed to :func:`~registration.detection.detect_spheres` and
        :func:`~registration.matching.register.register_points` unchanged.
    default_target_distance_mm : float
        Without targets, the TRE is predicted at the 6 points this far from the phantom centre
        along ±x, ±y, ±z of the robot frame.
    """

    detection: DetectionParams = field(default_factory=DetectionParams)
    registration: RegistrationParams = field(default_factory=RegistrationParams)
    default_target_distance_mm: float = 150.0


@dataclass(frozen=True, eq=False)
class SpherePair:
    """The phantom's spheres seen from both sides of one scan.

    Attributes
    ----------
    detection : DetectionResult
    robot_mm : ndarray, shape (N, 3), float64
        Every filled hole's centre in the robot frame, mm, in phantom sphere order.
    image_mm : ndarray, shape (M, 3), float64
        The detected centres in the image frame (LPS), mm, in detection order.
    centre_robot_mm : ndarray, shape (3,), float64
        The phantom frame's origin in the robot frame, mm.
    timings_s : mapping
        ``detect_s``.
    """

    detection: DetectionResult
    robot_mm: F64
    image_mm: F64
    centre_robot_mm: F64
    timings_s: Mapping[str, float] = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class ScanRegistration:
    """An accepted registration of one scan and where its predicted TRE was evaluated.

    Attributes
    ----------
    spheres : SpherePair
    result : RegistrationResult
        ``image_from_robot``, FRE, the matches; its ``predicted_tre_mm`` is at the default targets.
    targets_image_mm : ndarray, shape (T, 3), float64
        The targets the TRE is reported at, image frame (LPS), mm: those given, else the default
        targets mapped through ``result.image_from_robot``.
    predicted_tre_mm : ndarray, shape (T,), float64
        Fitzpatrick's predicted TRE at ``targets_image_mm``.
    targets_given : bool
        True when the caller gave the targets.
    timings_s : mapping
        ``detect_s``, ``register_s``.
    """

    spheres: SpherePair
    result: RegistrationResult
    targets_image_mm: F64
    predicted_tre_mm: F64
    targets_given: bool
    timings_s: Mapping[str, float] = field(default_factory=dict)


def default_targets_robot_mm(centre_robot_mm: ArrayLike, distance_mm: float) -> F64:
    """The 6 points ``distance_mm`` from ``centre_robot_mm`` along ±x, ±y, ±z of the robot frame.

    Returns
    -------
    ndarray, shape (6, 3), float64
        Robot frame, mm.
    """
    offsets = np.vstack([np.eye(3), -np.eye(3)]) * distance_mm
    return np.asarray(np.asarray(centre_robot_mm, dtype=np.float64).reshape(1, 3) + offsets, dtype=np.float64)


def locate_spheres(
    volume: Volume,
    joints_rad: ArrayLike,
    robot_model: RobotModel,
    tool0_from_phantom: ArrayLike,
    phantom: Phantom,
    detection: DetectionParams,
) -> SpherePair:
    """Detect the spheres in ``volume`` and compute where the robot says they are.

    Raises
    ------
    DetectionError, KinematicsError, FrameError
        From detection, the joints (count, limits) or a non-rigid ``tool0_from_phantom``.
    """
    t = time.perf_counter()
    det = detect_spheres(volume, detection)
    detect_s = time.perf_counter() - t
    robot_mm = sphere_centres_robot_mm(
        robot_model, joints_rad, tool0_from_phantom, phantom.centres_phantom_mm
    )
    robot_from_phantom = robot_model.robot_from_tool0(joints_rad) @ np.asarray(
        tool0_from_phantom, dtype=np.float64
    )
    return SpherePair(
        detection=det,
        robot_mm=np.asarray(robot_mm, dtype=np.float64),
        image_mm=np.asarray(det.centres_image_mm, dtype=np.float64).reshape(-1, 3),
        centre_robot_mm=np.asarray(robot_from_phantom[:3, 3], dtype=np.float64),
        timings_s={"detect_s": detect_s},
    )


def register_scan(
    volume: Volume,
    joints_rad: ArrayLike,
    robot_model: RobotModel,
    tool0_from_phantom: ArrayLike,
    phantom: Phantom,
    params: PipelineParams = PipelineParams(),
    targets_image_mm: ArrayLike | None = None,
) -> ScanRegistration:
    """Register one scan of the phantom held by the robot at ``joints_rad``.

    Parameters
    ----------
    volume : Volume
        The loaded scan.
    joints_rad : array_like, shape (n_joints,)
        The joints during the scan, rad.
    robot_model : RobotModel
    tool0_from_phantom : array_like, shape (4, 4)
        The connecting rod, mm.
    phantom : Phantom
    params : PipelineParams
    targets_image_mm : array_like, shape (T, 3), optional
        Where to predict the TRE, image frame (LPS), mm (e.g. planned screw entry points).
        Fitzpatrick's formula needs them in the fiducials' frame, so they are mapped back
        through the registration just computed.  Default: the 6 default targets.

    Raises
    ------
    RegistrationError
        Refused (too few spheres, ambiguous, mirrored, FRE over the gate, ...).
    DetectionError, KinematicsError
    """
    spheres = locate_spheres(volume, joints_rad, robot_model, tool0_from_phantom, phantom, params.detection)
    default_targets = default_targets_robot_mm(spheres.centre_robot_mm, params.default_target_distance_mm)
    t = time.perf_counter()
    res = register_points(
        spheres.robot_mm,
        spheres.image_mm,
        params=params.registration,
        targets_robot_mm=default_targets,
        phantom=phantom,
    )
    given = targets_image_mm is not None and len(np.asarray(targets_image_mm)) > 0
    if given:
        targets_img = np.asarray(targets_image_mm, dtype=np.float64).reshape(-1, 3)
        targets_robot = apply(invert(res.image_from_robot), targets_img)
        tre = predicted_tre_mm(res.fle_mm, spheres.robot_mm[res.robot_indices], targets_robot)
    else:
        targets_img = apply(res.image_from_robot, default_targets)
        tre = np.asarray(res.predicted_tre_mm, dtype=np.float64)
    register_s = time.perf_counter() - t
    return ScanRegistration(
        spheres=spheres,
        result=res,
        targets_image_mm=targets_img,
        predicted_tre_mm=np.asarray(tre, dtype=np.float64),
        targets_given=given,
        timings_s={**spheres.timings_s, "register_s": register_s},
    )


def verify_scan(
    volume: Volume,
    joints_rad: ArrayLike,
    robot_model: RobotModel,
    tool0_from_phantom: ArrayLike,
    phantom: Phantom,
    image_from_robot: ArrayLike,
    params: PipelineParams = PipelineParams(),
) -> tuple[SpherePair, VerificationResult]:
    """Per-sphere errors of ``image_from_robot`` (4 × 4, mm) on a second scan at ``joints_rad``.

    Raises
    ------
    RegistrationError
        Too few spheres matched within the gate.
    DetectionError, KinematicsError
    """
    spheres = locate_spheres(volume, joints_rad, robot_model, tool0_from_phantom, phantom, params.detection)
    res = verify_registration(
        image_from_robot, spheres.robot_mm, spheres.image_mm, params=params.registration
    )
    return spheres, res
