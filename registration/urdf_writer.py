"""Moved to :mod:`registration.calibration.urdf`; this old path lasts one release (CHANGELOG.md)."""

import sys

from registration.calibration import urdf as _moved

sys.modules[__name__] = _moved
