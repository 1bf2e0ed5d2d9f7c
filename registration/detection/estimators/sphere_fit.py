"""Model-based sub-voxel sphere centre: a blurred, saturated ball fitted to the raw voxels.

The reconstruction of a metal sphere of known radius R (the phantom file's diameter / 2) is
modelled as a uniform ball convolved with an isotropic Gaussian PSF of width σ, scaled, offset by
the local background and clipped at the export's saturation value::

    v(x) = min(bg + A · b(|x − c|; R, σ), v_sat)

with the closed form of a Gaussian-blurred ball (the radial profile of ``1_{|x|≤R} * G_σ``)::

    b(r) = ½[erf((R − r)/(σ√2)) + erf((R + r)/(σ√2))]
           − σ/(r√(2π)) · [exp(−(R − r)²/(2σ²)) − exp(−(R + r)²/(2σ²))]

The centre c (3), A, bg and σ are found by robust least squares (``soft_l1`` loss with a scale
of a few hundred HU, so streaks and bloom tails count far less than in a centroid).  The
saturated core carries no position information; the fit is decided by the unsaturated edge
all around the sphere, which is where the centroid is biased by one-sided streak tails.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Final

import numpy as np

from registration.arrays import F64

SQRT2: Final = math.sqrt(2.0)
SQRT2PI: Final = math.sqrt(2.0 * math.pi)
SMALL_R_MM: Final = 1e-6
"""Below this distance from the centre the blurred-ball profile uses its r → 0 limit."""


@dataclass(frozen=True)
class SphereFit:
    """A fitted sphere model (voxel-index frame of the crop it was fitted on).

    Attributes
    ----------
    centre_mm : ndarray, shape (3,), float64
        Centre in the coordinates the voxels were given in (mm, axis order of ``coords_mm``).
    sigma_mm, amplitude_hu, background_hu : float
        PSF width, ball contrast before clipping and local background.
    rms_hu : float
        RMS residual over the fitted voxels.
    ok : bool
        The optimiser converged and σ, A stayed inside their bounds' interior.
    reason : str
        Why not ``ok`` ("" when ok).
    """

    centre_mm: F64
    sigma_mm: float
    amplitude_hu: float
    background_hu: float
    rms_hu: float
    ok: bool
    reason: str = ""


def blurred_ball(r_mm: F64, radius_mm: float, sigma_mm: float) -> F64:
    """Radial profile (0 … 1) of a unit ball of ``radius_mm`` convolved with a Gaussian of ``sigma_mm``."""
    from scipy.special import erf  # here, not at module level: see fit_sphere_model

    r = np.maximum(np.asarray(r_mm, dtype=np.float64), SMALL_R_MM)
    s = sigma_mm
    a = (radius_mm - r) / (s * SQRT2)
    b = (radius_mm + r) / (s * SQRT2)
    tail = s / (r * SQRT2PI) * (np.exp(-(a * a)) - np.exp(-(b * b)))
    return np.asarray(0.5 * (erf(a) + erf(b)) - tail, dtype=np.float64)


@dataclass(frozen=True)
class FitParams:
    """Bounds and loss of :func:`fit_sphere_model` (mm and HU).

    Attributes
    ----------
    sigma_range_mm : tuple of float
        PSF σ allowed: the O-arm's 0.65–0.8 mm FWHM (Uneri et al. 2018, doi:10.1002/mp.13167) is
        σ ≈ 0.3 mm; slice integration and detector blur add to it; 0.1 … 1.5 mm brackets every
        preset with room.
    loss_scale_hu : float
        ``soft_l1`` scale: residuals beyond it count linearly, not quadratically.  Noise in the
        realistic presets is ≈ 50–100 HU, streaks near metal several hundred: 200 HU.
    max_shift_mm : float
        The centre may move at most this far from the start (the start is a centroid within a
        voxel or two of the truth); a larger move is a failed fit.
    """

    sigma_range_mm: tuple[float, float] = (0.1, 1.5)
    loss_scale_hu: float = 200.0
    max_shift_mm: float = 1.5


def fit_sphere_model(
    values_hu: F64,
    coords_mm: F64,
    start_mm: F64,
    radius_mm: float,
    saturation_hu: float,
    params: FitParams = FitParams(),
) -> SphereFit:
    """Fit the blurred, saturated ball to voxel values.

    Parameters
    ----------
    values_hu : ndarray, shape (V,), float64
        Raw voxel values (HU).
    coords_mm : ndarray, shape (V, 3), float64
        Voxel centres in mm (any Cartesian frame, e.g. voxel index × spacing).
    start_mm : ndarray, shape (3,), float64
        Starting centre in the same frame.
    radius_mm : float
        Nominal sphere radius (phantom file).
    saturation_hu : float
        Value at which the export clips (3071 HU for 12-bit CT); the model is clipped there too.
    """
    # scipy.optimize costs ~0.3 s to import; only the ``model`` method needs it, so ``oarmreg
    # detect`` with the default method does not pay for it (benchmarks/bench_detect_process.py).
    from scipy.optimize import least_squares

    v = np.asarray(values_hu, dtype=np.float64)
    x = np.asarray(coords_mm, dtype=np.float64)
    start = np.asarray(start_mm, dtype=np.float64)
    bg0 = float(np.percentile(v, 25))
    a0 = max(float(v.max()) - bg0, 1.0)
    lo_s, hi_s = params.sigma_range_mm
    p0 = np.array([*start, 0.35, a0, bg0])
    lower = np.array([*(start - params.max_shift_mm), lo_s, 0.1 * a0, bg0 - 2000.0])
    upper = np.array([*(start + params.max_shift_mm), hi_s, 20.0 * a0 + 1.0, bg0 + 2000.0])

    def residual(p: F64) -> F64:
        r = np.sqrt(np.sum((x - p[:3]) ** 2, axis=1))
        model = np.minimum(p[5] + p[4] * blurred_ball(r, radius_mm, float(p[3])), saturation_hu)
        return np.asarray(model - v, dtype=np.float64)

    sol: Any = least_squares(
        residual, p0, bounds=(lower, upper), loss="soft_l1", f_scale=params.loss_scale_hu, x_scale="jac"
    )
    p = np.asarray(sol.x, dtype=np.float64)
    rms = float(np.sqrt(np.mean(sol.fun**2)))
    reason = ""
    shift = float(np.linalg.norm(p[:3] - start))
    if not sol.success:
        reason = f"optimiser did not converge ({sol.message})"
    elif shift >= params.max_shift_mm * 0.999:
        reason = f"centre moved {shift:.2f} mm from the start (limit {params.max_shift_mm} mm)"
    elif not lo_s * 1.001 < p[3] < hi_s * 0.999:
        reason = f"PSF σ {p[3]:.2f} mm at a bound of {params.sigma_range_mm} mm"
    return SphereFit(p[:3].copy(), float(p[3]), float(p[4]), float(p[5]), rms, reason == "", reason)
