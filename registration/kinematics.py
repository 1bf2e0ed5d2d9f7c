"""Moved to :mod:`registration.model.kinematics`; this old path lasts one release (CHANGELOG.md)."""

import sys

from registration.model import kinematics as _moved

sys.modules[__name__] = _moved
