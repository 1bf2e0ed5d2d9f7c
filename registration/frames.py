"""Moved to :mod:`registration.model.frames`; this old path lasts one release (CHANGELOG.md)."""

import sys

from registration.model import frames as _moved

sys.modules[__name__] = _moved
