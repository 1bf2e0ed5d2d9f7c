"""Metal-sphere detection in a CT volume: the spheres' centres in the image frame, and why not.

The modules follow the data, in order (:func:`detect_spheres` in :mod:`.detect` runs them):

1. :mod:`.candidates`: one threshold pass over the volume, the hits grouped and labelled into
   blobs; an oversized blob is split into sphere cores;
2. :mod:`.rejections`: a blob that is not sphere-sized or bright enough is refused with a reason;
3. :mod:`.centroid`: the intensity-weighted sub-voxel centroid on the raw volume and its
   per-slice profile;
4. :mod:`.fov` and :mod:`.refine`: the circular field of view and the volume's edges; a sphere
   near one is re-measured with a symmetric window, or refused as cut;
5. :mod:`.cross_check`: circles in the sphere's slices (Bai 2018's moment invariants, after MAR),
   the cross-check of the 3-D centre;
6. :mod:`.estimators`: the centre estimator named by ``DetectionParams.method`` (one module each,
   looked up by name and imported on first use); two centres closer than the phantom allows are
   resolved last (:mod:`.rejections`).

:mod:`.params` holds the settings and :func:`params_for_spheres`, the one function that chooses
them from the phantom's spheres; :mod:`.records` what the detection returns.  The chain follows
Bai et al. 2018 (doi:10.1088/1742-6596/1016/1/012006, §2.2), with 3-D estimators on the raw
volume measured more accurate (``docs/validation.md``, "Sphere detection").
"""

from registration.detection.detect import detect_spheres
from registration.detection.estimators import METHODS
from registration.detection.params import (
    BACKGROUND_MODELS,
    METHOD_FOR_MATERIAL,
    DetectionParams,
    method_for_material,
    params_for_spheres,
)
from registration.detection.records import DetectedSphere, DetectionResult, Rejection
from registration.detection.timing import TIMED_STAGES, StageTimer

__all__ = [
    "BACKGROUND_MODELS",
    "METHODS",
    "METHOD_FOR_MATERIAL",
    "TIMED_STAGES",
    "DetectedSphere",
    "DetectionParams",
    "DetectionResult",
    "Rejection",
    "StageTimer",
    "detect_spheres",
    "method_for_material",
    "params_for_spheres",
]
