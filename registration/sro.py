"""Moved to :mod:`registration.io.sro`; this old path lasts one release (CHANGELOG.md)."""

import sys

from registration.io import sro as _moved

sys.modules[__name__] = _moved
