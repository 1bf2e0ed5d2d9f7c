"""Moved to :mod:`registration.matching.correspondence`; this old path lasts one release (CHANGELOG.md)."""

import sys

from registration.matching import correspondence as _moved

sys.modules[__name__] = _moved
