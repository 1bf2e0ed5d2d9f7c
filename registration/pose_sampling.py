"""Moved to :mod:`registration.calibration.sampling`; this old path lasts one release (CHANGELOG.md)."""

import sys

from registration.calibration import sampling as _moved

sys.modules[__name__] = _moved
