"""Moved to :mod:`registration.imaging.scan_geometry`; this old path lasts one release (CHANGELOG.md)."""

import sys

from registration.imaging import scan_geometry as _moved

sys.modules[__name__] = _moved
