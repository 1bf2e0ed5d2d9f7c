"""Moved to :mod:`registration.model.stillness`; this old path lasts one release (CHANGELOG.md)."""

import sys

from registration.model import stillness as _moved

sys.modules[__name__] = _moved
