"""Moved to :mod:`registration.io.points`; this old path lasts one release (CHANGELOG.md)."""

import sys

from registration.io import points as _moved

sys.modules[__name__] = _moved
