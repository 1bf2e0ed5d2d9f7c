"""Array type aliases shared by the five packages (one definition, not one per module)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
"""A float64 array of any shape (the shape is in each function's docstring)."""
