"""The project's exception families.

Every failure a user can cause is one of these, with a message that says what
was expected, what was found and what to try.  These errors know nothing of
HTTP or exit codes: the service maps each family to an HTTP status (problem
details, RFC 9457) and a CLI exit code in one table, :mod:`service.error_map`.
Robot-link errors live in :mod:`drivers.errors` (``drivers`` may not import
this package).
"""

from __future__ import annotations


class OarmRegError(Exception):
    """Base of every error a user can cause."""

    title: str = "Invalid input"


class ConfigError(OarmRegError):
    """A configuration file or value is wrong (TOML, phantom, URDF, settings)."""

    title = "Configuration error"


class PhantomDefinitionError(ConfigError):
    """The phantom definition is invalid (duplicate holes, symmetric pattern, ...)."""

    title = "Invalid phantom definition"


class DicomSeriesError(OarmRegError):
    """A DICOM folder does not hold one consistent, loadable CT series."""

    title = "Unusable DICOM series"


class DetectionError(OarmRegError):
    """Sphere detection could not produce usable centres."""

    title = "Sphere detection failed"


class PointsFileError(OarmRegError):
    """A points / registration / targets JSON file is malformed."""

    title = "Invalid points file"


class InputFileUnreadableError(OarmRegError):
    """An input file (points, joints, poses, registration JSON) is missing or cannot be read: a
    file-system problem, not bad content."""

    title = "Cannot read input file"


class KinematicsError(OarmRegError):
    """Joint values are outside the model (wrong count, NaN, joint limits)."""

    title = "Kinematics error"


class RegistrationError(OarmRegError):
    """A registration was refused.  Subclasses say why."""

    title = "Registration refused"


class TooFewSpheresError(RegistrationError):
    title = "Too few spheres"


class AmbiguousMatchError(RegistrationError):
    title = "Ambiguous sphere correspondence"


class MirroredInputError(RegistrationError):
    title = "Mirrored input"


class DegenerateConfigurationError(RegistrationError):
    title = "Degenerate sphere configuration"


class RobotMovedError(RegistrationError):
    """A joint deviated more than ``stillness.max_deviation_rad`` during the scan window."""

    title = "Robot moved during the scan"


class JointHistoryIncompleteError(RegistrationError):
    """The joint history does not cover the scan window (not watched, frames missing, reconnect):
    the robot's stillness is unknown, which is not the same as "moved"."""

    title = "Joint history incomplete"


class PhantomMismatchError(RegistrationError):
    """The scan does not look like the phantom file: far more spheres detected than it has, or the
    best pose explains only a small share of the detections.  Refused unless the user confirms the
    phantom file (``--phantom-confirmed``, ``"phantom_confirmed": true``)."""

    title = "Check the phantom file"


class AccuracyGateError(RegistrationError):
    """A quality figure exceeded its configured gate (FRE, verification error)."""

    title = "Accuracy gate failed"


class TooFewWithinGateError(TooFewSpheresError):
    """The best pose has no distinct runner-up but too few spheres within the fixed gate (loose fit)."""

    title = "Too few spheres within the gate"


class ImproperRotationError(RegistrationError):
    """The registered rotation is not proper (det R ≠ +1): an internal fault, refused, never stored."""

    title = "Improper rotation"


class PosesFileError(PointsFileError):
    """A calibration POSES.json or a JOINTS.json is malformed (too few poses, wrong joint count)."""

    title = "Invalid poses file"


# raised by registration.model.frames


class NotRigidError(OarmRegError):
    title = "Transform is not rigid"


# raised by registration.matching.records


class PriorMismatchError(RegistrationError):
    """No pose within the orientation prior's tolerance explains the detections."""

    title = "Orientation prior not met"


# raised by registration.matching.rigid


class PointSetError(OarmRegError):
    """A point set passed to the registration has the wrong shape or non-finite values."""

    title = "Invalid point set"


# raised by registration.matching.prereg


class PreregistrationError(RegistrationError):
    """The four marks do not define a usable rigid pre-registration."""

    title = "Pre-registration refused"


# raised by registration.matching.face_offset


class FaceOffsetError(RegistrationError):
    """The spheres sit deeper or higher in their holes, all together, than the phantom file says."""

    title = "Face offset out of bounds"


# raised by registration.imaging.scan_geometry


class SeriesGeometryError(RegistrationError):
    title = "Series geometry missing or malformed"


# raised by registration.calibration.records


class CalibrationError(RegistrationError):
    """A calibration was refused.  Subclasses say why."""

    title = "Calibration refused"


class TooFewPosesError(CalibrationError):
    title = "Too few calibration poses"


class SessionMismatchError(CalibrationError):
    title = "Scans from different O-arm placements"


class NotIdentifiableError(CalibrationError):
    title = "Calibration parameters not identifiable from these poses"


class OutlierPoseError(CalibrationError):
    title = "Calibration pose inconsistent with the others"


# raised by registration.calibration.planner


class PlanningError(RegistrationError):
    title = "Cannot plan calibration poses"


# raised by registration.io.sro


class SroError(OarmRegError):
    """A Spatial Registration object cannot be built from these inputs."""

    title = "Cannot build the DICOM Spatial Registration object"
