"""Moved to :mod:`registration.matching.register`; this old path lasts one release (CHANGELOG.md)."""

import sys

from registration.matching import register as _moved

sys.modules[__name__] = _moved
