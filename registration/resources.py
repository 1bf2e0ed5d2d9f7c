"""Moved to :mod:`registration.io.resources`; this old path lasts one release (CHANGELOG.md)."""

import sys

from registration.io import resources as _moved

sys.modules[__name__] = _moved
