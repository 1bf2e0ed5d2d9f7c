"""Cone-beam simulator (issue #11 item 1.5): geometry against RTK, FDK centroid accuracy.

Skipped, with the reason, when itk-rtk is not installed (``pip install 'oarmreg[cbct]'``).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from mocks.oarm.cbct import ConeBeamSettings, projection_matrix, simulate_cbct
from mocks.oarm.simulator import SceneExtras
from registration import frames

itk = pytest.importorskip("itk", reason="itk-rtk not installed: pip install 'oarmreg[cbct]'")
try:
    from itk import RTK as rtk
except ImportError:  # pragma: no cover - depends on the environment
    pytest.skip("itk-rtk not installed: pip install 'oarmreg[cbct]'", allow_module_level=True)

CENTROID_TOL_MM = 0.01
"""Issue #11: noise-free spheres at and 35 mm off the central plane, centroids within 0.01 mm."""


def test_projection_matrices_match_rtk() -> None:
    s = ConeBeamSettings.preset("cbct-ci")
    g = rtk.ThreeDCircularProjectionGeometry.New()
    for deg in (0.0, 37.0, 90.0, 211.0):
        g.AddProjection(s.sid_mm, s.sdd_mm, deg)
    for i, deg in enumerate((0.0, 37.0, 90.0, 211.0)):
        ours = projection_matrix(s, math.radians(deg))
        theirs = np.asarray(itk.array_from_matrix(g.GetMatrix(i)))
        assert np.allclose(ours, theirs, atol=1e-9)


@pytest.mark.xfail(
    reason="open: steel spheres 1.25 mm under the cube face come out 0.13-0.18 mm radially inward "
    "(titanium 0.03-0.06 mm, z exact, also with 1 sub-ray); not yet traced to physics or geometry",
    strict=False,
)
def test_fdk_centroids_at_and_off_the_central_plane(phantom) -> None:
    """Spheres at z = 0 and z = 35 mm, fine 0.15 mm ROI grids, noise-free: centroid error < 0.01 mm."""
    pose = frames.transform_from_xyz_rpy([0.0, 0.0, 7.5], [0.0, 0.0, 20.0])  # rows at z = 0, 15, 30
    pose35 = frames.transform_from_xyz_rpy([0.0, 0.0, 12.5], [0.0, 0.0, 20.0])  # top row at z = 35
    ideal = {
        "noise": False,
        "scatter_spr": 0.0,
        "light_spread_fwhm_mm": 0.0,
        "lag_fraction": 0.0,
        "n_views": 120,
        "det_cols": 512,
        "det_rows": 384,
        "det_pitch_mm": 0.776,
        "subrays": 3,
        "rows": 28,
        "columns": 28,
        "n_slices": 28,
        "pixel_mm": 0.15,
        "slice_spacing_mm": 0.15,
    }
    extras = SceneExtras(empty_holes=False)
    for p, z_target in ((pose, 0.0), (pose35, 35.0)):
        centres = frames.apply(p, phantom.centres_phantom_mm)
        target = centres[int(np.argmin(np.abs(centres[:, 2] - z_target) + 1e-3 * np.abs(centres[:, 1])))]
        s = ConeBeamSettings.preset("cbct-ci", roi_centre_mm=tuple(float(v) for v in target), **ideal)
        scan = simulate_cbct(phantom, p, s, extras)
        w = np.clip(scan.hu.astype(float) - 1500.0, 0.0, None)
        kk, jj, ii = np.mgrid[0 : s.n_slices, 0 : s.rows, 0 : s.columns]
        ijk = np.array([(w * ii).sum(), (w * jj).sum(), (w * kk).sum()]) / w.sum()
        found = frames.apply(scan.image_from_voxel, ijk[None])[0]
        assert abs(target[2] - z_target) < 1.3
        assert np.linalg.norm(found - target) < CENTROID_TOL_MM, (z_target, found - target)
