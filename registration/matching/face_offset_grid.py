"""The face offset of a scan with no robot points (``oarmreg detect``): fitted over the phantom's holes.

:func:`grid_face_offset` pairs the detections with the phantom's filled holes through the
registration and keeps the β of :mod:`registration.matching.face_offset` in the detection record.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from registration.detection.records import DetectionResult, FaceOffset
from registration.errors import PointSetError, RegistrationError
from registration.matching.records import RegistrationParams
from registration.matching.register import register_points
from registration.model.phantom import Phantom


def grid_face_offset(detection: DetectionResult, phantom: Phantom) -> DetectionResult:
    """``detection`` with the face offset fitted over ``phantom``'s holes (``oarmreg detect``).

    Without robot points the detections are paired with the phantom's filled holes by the
    registration itself (:func:`registration.matching.register.register_points` with the phantom's
    centres as the model), allowing a symmetric twin: the grid's symmetries map faces onto faces,
    so every twin gives the same β.  When no pairing is found (too few spheres, a mirrored scan,
    a residual over the gate) the result carries the reason instead, and when |β| is out of
    bounds the FaceOffsetError's message.
    """
    centres = detection.centres_image_mm
    try:
        reg = register_points(
            phantom.centres_phantom_mm,
            centres,
            params=RegistrationParams(min_runner_up_margin=0, face_offset_fit=True),
            phantom=phantom,
        )
    except (RegistrationError, PointSetError) as e:
        return dataclasses.replace(detection, face_offset=None, face_offset_reason=str(e))
    if reg.face_offset_mm is None:
        return dataclasses.replace(detection, face_offset=None, face_offset_reason="not fitted")
    rot = reg.image_from_robot[:3, :3]
    corrected = np.full_like(centres, np.nan)
    axes = phantom.axes_phantom[reg.robot_indices] @ rot.T
    corrected[reg.image_indices] = centres[reg.image_indices] - reg.face_offset_mm * axes
    se = math.nan if reg.face_offset_se_mm is None else reg.face_offset_se_mm
    return dataclasses.replace(
        detection, face_offset=FaceOffset(reg.face_offset_mm, se, corrected), face_offset_reason=""
    )
