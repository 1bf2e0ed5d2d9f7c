"""Moved to :mod:`registration.imaging.mar`; this old path lasts one release (CHANGELOG.md)."""

import sys

from registration.imaging import mar as _moved

sys.modules[__name__] = _moved
