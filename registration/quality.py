"""Moved to :mod:`registration.matching.quality`; this old path lasts one release (CHANGELOG.md)."""

import sys

from registration.matching import quality as _moved

sys.modules[__name__] = _moved
