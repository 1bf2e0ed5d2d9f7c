"""Moved to :mod:`registration.matching.rigid`; this old path lasts one release (CHANGELOG.md)."""

import sys

from registration.matching import rigid as _moved

sys.modules[__name__] = _moved
