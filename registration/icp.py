"""Moved to :mod:`registration.matching.icp`; this old path lasts one release (CHANGELOG.md)."""

import sys

from registration.matching import icp as _moved

sys.modules[__name__] = _moved
