"""Step 6 of the detection: the centre estimators, one module each, found by name.

Every estimator starts from what the detection measured of a sphere
(:class:`.base.MeasuredSphere`: the edge-refined sub-voxel centroid, the slice circles, the raw
volume around it) and owns the two steps that turn it into a centre (:class:`.base.CentreEstimator`):
``prepare`` gathers what it looks at (its own record: a ray fit, a voxel patch, the circles) and
``estimate`` returns the centre or why there is none.  The detection looks the estimator up in
:data:`ESTIMATOR_MODULES` by ``DetectionParams.method`` and imports its module only then
(:func:`.base.centre_estimator`), so a detection pays only for the estimator it runs (the
``model`` fit's optimiser stays out of ``oarmreg detect``).  A new estimator is a module with an
``ESTIMATOR`` and a row here.

========== =================================================================================
subvoxel   the intensity-weighted centroid, slice coordinate from its per-slice profile
paper      Bai 2018: in-plane mean of the circle centres, depth by Pythagoras
model      a blurred, saturated ball fitted to the raw voxels (:mod:`.sphere_fit`)
core       windowed centroids of an opaque sphere's saturated core (:mod:`.core_centroid`)
rays       the centre of the sphere's outline at 70 % of its contrast (:mod:`.ray_fit`)
========== =================================================================================

Which estimator each sphere material gets, and the measurements behind it:
:data:`registration.detection.params.METHOD_FOR_MATERIAL`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Final

ESTIMATOR_MODULES: Final[Mapping[str, str]] = {
    "subvoxel": "registration.detection.estimators.subvoxel",
    "model": "registration.detection.estimators.model",
    "paper": "registration.detection.estimators.paper",
    "core": "registration.detection.estimators.core",
    "rays": "registration.detection.estimators.rays",
}
"""Module of each centre estimator (it defines ``ESTIMATOR``), by ``DetectionParams.method``."""

METHODS: Final = tuple(ESTIMATOR_MODULES)
"""The centre estimators' names, in table order."""
