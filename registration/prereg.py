"""Moved to :mod:`registration.matching.prereg`; this old path lasts one release (CHANGELOG.md)."""

import sys

from registration.matching import prereg as _moved

sys.modules[__name__] = _moved
