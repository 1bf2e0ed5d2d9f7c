"""The project's exception families.

Every failure a user can cause is one of these, with a message that says what
was expected, what was found and what to try.  ``exit_code`` is what the CLI
returns for it; ``http_status`` is what the service answers (problem details,
RFC 9457).  Robot-link errors live in :mod:`drivers.errors` (``drivers`` may not
import this package) and carry the same two attributes.

Exit codes (documented in the README):

==  ==========================================================
0   success
2   usage error (argparse)
3   configuration error (bad TOML, bad phantom, bad URDF)
4   input data error (DICOM series, points file, detection)
5   robot link error (no link, timeout, protocol)
6   registration refused (ambiguous, mirrored, too few spheres,
    degenerate, robot moved)
7   accuracy gate failed (FRE / verification over threshold)
==  ==========================================================
"""

from __future__ import annotations

EXIT_OK = 0
EXIT_USAGE = 2
EXIT_CONFIG = 3
EXIT_INPUT = 4
EXIT_ROBOT_LINK = 5
EXIT_REFUSED = 6
EXIT_ACCURACY = 7


class OarmRegError(Exception):
    """Base of every error a user can cause."""

    exit_code: int = EXIT_INPUT
    http_status: int = 422
    title: str = "Invalid input"


class ConfigError(OarmRegError):
    """A configuration file or value is wrong (TOML, phantom, URDF, settings)."""

    exit_code = EXIT_CONFIG
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


class KinematicsError(OarmRegError):
    """Joint values are outside the model (wrong count, NaN, joint limits)."""

    title = "Kinematics error"


class RegistrationError(OarmRegError):
    """A registration was refused.  Subclasses say why."""

    exit_code = EXIT_REFUSED
    http_status = 409
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
    title = "Robot moved during the scan"


class AccuracyGateError(RegistrationError):
    """A quality figure exceeded its configured gate (FRE, verification error)."""

    exit_code = EXIT_ACCURACY
    title = "Accuracy gate failed"


class TooFewWithinGateError(TooFewSpheresError):
    """The best pose has no distinct runner-up but too few spheres within the fixed gate (loose fit)."""

    title = "Too few spheres within the gate"


class ImproperRotationError(RegistrationError):
    """The registered rotation is not proper (det R ≠ +1): an internal fault, refused, never stored."""

    title = "Improper rotation"
