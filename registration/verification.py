"""Moved to :mod:`registration.matching.verification`; this old path lasts one release (CHANGELOG.md)."""

import sys

from registration.matching import verification as _moved

sys.modules[__name__] = _moved
