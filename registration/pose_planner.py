"""Moved to :mod:`registration.calibration.planner`; this old path lasts one release (CHANGELOG.md)."""

import sys

from registration.calibration import planner as _moved

sys.modules[__name__] = _moved
