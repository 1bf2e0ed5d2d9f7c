"""Moved to :mod:`registration.model.phantom`; this old path lasts one release (CHANGELOG.md)."""

import sys

from registration.model import phantom as _moved

sys.modules[__name__] = _moved
