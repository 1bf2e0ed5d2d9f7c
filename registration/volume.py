"""Moved to :mod:`registration.imaging.volume`; this old path lasts one release (CHANGELOG.md)."""

import sys

from registration.imaging import volume as _moved

sys.modules[__name__] = _moved
