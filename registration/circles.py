"""Moved to :mod:`registration.imaging.circles`; this old path lasts one release (CHANGELOG.md)."""

import sys

from registration.imaging import circles as _moved

sys.modules[__name__] = _moved
