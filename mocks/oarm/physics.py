"""X-ray physics tables for the O-arm simulator: spectrum and attenuation.

Mass attenuation coefficients μ/ρ (cm²/g, total with coherent scattering) are
hard-coded from the NIST X-ray mass attenuation tables (J. H. Hubbell and
S. M. Seltzer, NISTIR 5632, doi:10.18434/T4D01F; the XCOM values agree to the
digits given) at the tabulated energies 30–150 keV and interpolated log-log to
the spectrum bins, as the tables' own documentation recommends.  Compounds
without a table row (POM, cancellous bone, stainless steel) use the mixture
rule μ/ρ = Σ wᵢ (μ/ρ)ᵢ over element mass fractions wᵢ.

Tungsten has its K edge (69.525 keV) inside the spectrum, so its table carries
the NIST values just below and just above the edge and the interpolation never
crosses it (:data:`_EDGE_TABLES`); a spectrum for tungsten carbide should put
a bin edge there (:data:`K_EDGE_BIN_EDGES_KEV`).

The spectrum is a Kramers-law tungsten bremsstrahlung spectrum (photon number
per keV ∝ (kVp − E)/E, H. A. Kramers, Phil. Mag. 46:836 (1923)) hardened by an
aluminium filter and weighted by E for an energy-integrating flat-panel
detector.  Characteristic tungsten lines (59, 67 keV) are ignored: they carry a
few per cent of the fluence and do not change the beam-hardening picture.
The O-arm's tube voltage (up to 120 kVp) and total filtration are not published
in a source found here; 120 kVp / 4 mm Al is an assumption (HVL ≈ 5.5 mm Al,
typical of CT beams).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

TABLE_ENERGIES_KEV = np.array([30.0, 40.0, 50.0, 60.0, 80.0, 100.0, 150.0])
"""Energies at which the NIST tables below are given (keV)."""

# NIST X-ray mass attenuation coefficients, μ/ρ in cm²/g at TABLE_ENERGIES_KEV
# (Hubbell & Seltzer, NISTIR 5632, tables 3 and 4).
_MU_RHO_CM2_G: dict[str, tuple[float, ...]] = {
    "H": (0.3570, 0.3458, 0.3355, 0.3260, 0.3091, 0.2944, 0.2651),
    "C": (0.2562, 0.2076, 0.1871, 0.1753, 0.1610, 0.1514, 0.1347),
    "O": (0.3779, 0.2585, 0.2132, 0.1907, 0.1678, 0.1551, 0.1361),
    "Al": (1.128, 0.5685, 0.3681, 0.2778, 0.2018, 0.1704, 0.1378),
    "Fe": (8.176, 3.629, 1.958, 1.205, 0.5952, 0.3717, 0.1964),
    # Water, liquid (table 4).
    "water": (0.3756, 0.2683, 0.2269, 0.2059, 0.1837, 0.1707, 0.1505),
    # Bone, cortical (ICRU-44), table 4.
    "bone_cortical": (1.331, 0.6655, 0.4242, 0.3148, 0.2229, 0.1855, 0.1480),
    # Titanium, Z = 22 (table 3); no absorption edge above 5 keV.
    "Ti": (4.972, 2.214, 1.213, 0.7661, 0.4052, 0.2721, 0.1649),
}

W_K_EDGE_KEV = 69.525
"""Tungsten K absorption edge (NIST table 3, Z = 74: 6.95250E-02 MeV)."""

# Elements whose tables need their own energies: (energies keV, μ/ρ cm²/g), an edge given twice
# (value below, value above).  Tungsten, Z = 74, NIST table 3 rows 30–150 keV.
_EDGE_TABLES: dict[str, tuple[tuple[float, ...], tuple[float, ...]]] = {
    "W": (
        (30.0, 40.0, 50.0, 60.0, W_K_EDGE_KEV, W_K_EDGE_KEV, 80.0, 100.0, 150.0),
        (22.73, 10.67, 5.949, 3.713, 2.552, 11.23, 7.810, 4.438, 1.581),
    ),
}


def _element_mu_rho(key: str, energies_kev: NDArray[np.float64]) -> NDArray[np.float64]:
    """μ/ρ (cm²/g) of one table entry, log-log interpolated without crossing an absorption edge."""
    e = np.asarray(energies_kev, dtype=np.float64)
    if key not in _EDGE_TABLES:
        table = np.log(np.asarray(_MU_RHO_CM2_G[key]))
        return np.asarray(np.exp(np.interp(np.log(e), np.log(TABLE_ENERGIES_KEV), table)), dtype=np.float64)
    te, tv = (np.asarray(v, dtype=np.float64) for v in _EDGE_TABLES[key])
    out = np.empty_like(e)
    # Split the table at repeated energies (edges) and interpolate each branch on its own side.
    cuts = [0, *(np.flatnonzero(np.diff(te) == 0) + 1).tolist(), len(te)]
    for a, b in itertools.pairwise(cuts):
        lo = -np.inf if a == 0 else te[a]
        hi = np.inf if b == len(te) else te[b]
        m = (e >= lo) & (e < hi)
        out[m] = np.exp(np.interp(np.log(e[m]), np.log(te[a:b]), np.log(tv[a:b])))
    return out


@dataclass(frozen=True)
class Material:
    """A material as density plus element / compound mass fractions."""

    name: str
    density_g_cm3: float
    mass_fractions: tuple[tuple[str, float], ...]

    def mu_rho_cm2_g(self, energies_kev: NDArray[np.float64]) -> NDArray[np.float64]:
        """Mass attenuation coefficient (cm²/g) at ``energies_kev`` (log-log interpolation)."""
        e = np.asarray(energies_kev, dtype=np.float64)
        out = np.zeros_like(e)
        for key, w in self.mass_fractions:
            out += w * _element_mu_rho(key, e)
        return out

    def mu_per_mm(self, energies_kev: NDArray[np.float64]) -> NDArray[np.float64]:
        """Linear attenuation coefficient (1/mm) at ``energies_kev``."""
        return self.mu_rho_cm2_g(energies_kev) * self.density_g_cm3 / 10.0


MATERIALS: dict[str, Material] = {
    "water": Material("water", 1.0, (("water", 1.0),)),
    # Polyoxymethylene (Delrin), (CH2O)n: H 6.71 %, C 40.00 %, O 53.29 % by mass; 1.41 g/cm³.
    "pom": Material("pom", 1.41, (("H", 0.0671), ("C", 0.4000), ("O", 0.5329))),
    # PMMA C5H8O2: H 8.05 %, C 59.98 %, O 31.96 %; 1.19 g/cm³ (NIST "Lucite" composition).
    "pmma": Material("pmma", 1.19, (("H", 0.0805), ("C", 0.5998), ("O", 0.3196))),
    "bone_cortical": Material("bone_cortical", 1.92, (("bone_cortical", 1.0),)),
    # Cancellous (trabecular) bone + marrow: 20 % cortical bone / 80 % water by mass, 1.12 g/cm³
    # (ICRU 46 spongiosa ≈ 1.18); gives ≈ +250…300 HU, the usual vertebral-body range.
    "bone_cancellous": Material("bone_cancellous", 1.12, (("bone_cortical", 0.20), ("water", 0.80))),
    # Stainless steel approximated by iron (Fe ≈ 70 % of AISI 304/316; Cr and Ni sit either side
    # of Fe in Z, so their μ/ρ average out within a few per cent); 7.9 g/cm³.
    "steel": Material("steel", 7.9, (("Fe", 1.0),)),
    "aluminium": Material("aluminium", 2.699, (("Al", 1.0),)),
    # Tungsten carbide WC: W 93.87 %, C 6.13 % by mass (stoichiometry, atomic masses 183.84 and
    # 12.011), 15.63 g/cm³ (sintered WC spheres, e.g. grade-10 WC ball specifications: 15.6 g/cm³;
    # WC-Co grades with 6 % Co are 14.9 g/cm³ and attenuate slightly less).  The issue asks for
    # ~15.6 g/cm³ and the NIST composition W 93.9 % / C 6.1 %.
    "tungsten_carbide": Material("tungsten_carbide", 15.63, (("W", 0.9387), ("C", 0.0613))),
    # Commercially pure titanium (grade 2), 4.51 g/cm³; Ti-6Al-4V (4.43 g/cm³) differs by < 3 % in μ.
    "titanium": Material("titanium", 4.51, (("Ti", 1.0),)),
}

SPHERE_MATERIALS = ("steel", "tungsten_carbide", "titanium")
"""Materials a phantom's spheres can be made of (registration/model/phantom.py lists the same names)."""

SCENE_MATERIALS = ("water", "plastic", "bone_cortical", "bone_cancellous", "steel", "sphere")
"""Material slots of the simulator's line-integral arrays (``plastic`` is POM or PMMA; ``sphere``
is the phantom's sphere material, one of :data:`SPHERE_MATERIALS`; ``steel`` is the rod)."""

DEFAULT_KVP = 120.0
"""O-arm maximum tube voltage (Medtronic O-arm O2 brochure: 40–120 kV); assumption, see module doc."""
DEFAULT_FILTER_AL_MM = 4.0
"""Total filtration in mm Al equivalent (assumption: gives HVL ≈ 5.5 mm Al at 120 kVp)."""
DEFAULT_BIN_EDGES_KEV = (35.0, 45.0, 55.0, 65.0, 75.0, 85.0, 95.0, 105.0, 120.0)
"""Eight energy bins 35–120 keV (≥ 4 bins between ~40 and 120 keV resolve beam hardening)."""
K_EDGE_BIN_EDGES_KEV = (35.0, 45.0, 55.0, 62.0, W_K_EDGE_KEV, 77.0, 85.0, 95.0, 105.0, 120.0)
"""Nine bins with an edge at tungsten's K edge, so no bin mixes μ from both sides of it."""


@dataclass(frozen=True, eq=False)
class Spectrum:
    """A discretised detected spectrum.

    Attributes
    ----------
    energies_kev : ndarray, shape (n_bins,)
        Representative (fluence-weighted mean) energy of each bin.
    weights : ndarray, shape (n_bins,)
        Fraction of the detected signal (energy-integrating) in each bin; sums to 1.
    """

    energies_kev: NDArray[np.float64]
    weights: NDArray[np.float64]

    @property
    def mean_energy_kev(self) -> float:
        return float(np.sum(self.energies_kev * self.weights))


def kramers_spectrum(
    kvp: float = DEFAULT_KVP,
    filter_al_mm: float = DEFAULT_FILTER_AL_MM,
    bin_edges_kev: tuple[float, ...] = DEFAULT_BIN_EDGES_KEV,
) -> Spectrum:
    """Filtered Kramers spectrum, energy-integrating detector weighting, binned.

    Parameters
    ----------
    kvp : float
        Tube voltage (kV); photons above it do not exist.
    filter_al_mm : float
        Aluminium filtration (mm).
    bin_edges_kev : tuple of float
        Increasing bin edges (keV); at least 5 edges (4 bins).
    """
    edges = np.asarray(bin_edges_kev, dtype=np.float64)
    if edges.size < 5 or np.any(np.diff(edges) <= 0):
        raise ValueError(f"need >= 4 increasing energy bins, got edges {bin_edges_kev}")
    e = np.arange(edges[0], min(edges[-1], kvp), 0.25) + 0.125
    fluence = np.clip(kvp - e, 0.0, None) / e  # Kramers: photons per keV
    fluence *= np.exp(-MATERIALS["aluminium"].mu_per_mm(e) * filter_al_mm)
    signal = fluence * e  # energy-integrating detector
    energies, weights = [], []
    for lo, hi in itertools.pairwise(edges):
        m = (e >= lo) & (e < hi)
        if not np.any(m) or signal[m].sum() <= 0:
            continue
        weights.append(signal[m].sum())
        energies.append(float(np.sum(e[m] * fluence[m]) / fluence[m].sum()))
    w = np.asarray(weights)
    return Spectrum(energies_kev=np.asarray(energies), weights=w / w.sum())


def attenuation_matrix_per_mm(
    spectrum: Spectrum, plastic: str = "pom", sphere: str = "steel"
) -> NDArray[np.float32]:
    """μ (1/mm) of each scene material (rows, :data:`SCENE_MATERIALS` order) at each bin (columns)."""
    if sphere not in SPHERE_MATERIALS:
        raise ValueError(f"sphere material {sphere!r} not one of {SPHERE_MATERIALS}")
    names = [{"plastic": plastic, "sphere": sphere}.get(m, m) for m in SCENE_MATERIALS]
    return np.stack([MATERIALS[n].mu_per_mm(spectrum.energies_kev) for n in names]).astype(np.float32)


@dataclass(frozen=True, eq=False)
class WaterCorrection:
    """Water beam-hardening linearisation (as every CT scanner applies before FBP).

    Maps a measured polychromatic log attenuation p to the monochromatic
    ``mu_ref_per_mm × L_water`` of the water path that would give it, so water
    reconstructs flat at 0 HU; other materials still harden (bone, steel).
    """

    p_table: NDArray[np.float32]
    corrected_table: NDArray[np.float32]
    mu_ref_per_mm: float

    def apply(self, p: NDArray[np.float32]) -> NDArray[np.float32]:
        out = np.interp(p, self.p_table, self.corrected_table)
        return np.asarray(out, dtype=np.float32)


def water_correction(spectrum: Spectrum, max_water_mm: float = 600.0) -> WaterCorrection:
    """Build the water linearisation table for ``spectrum``.

    The reference μ is the spectrum-weighted mean water μ (the slope of p at
    zero thickness), i.e. water's μ at the beam's effective energy.
    """
    mu_w = MATERIALS["water"].mu_per_mm(spectrum.energies_kev)
    lengths = np.linspace(0.0, max_water_mm, 4001)
    p = -np.log(np.exp(-np.outer(lengths, mu_w)) @ spectrum.weights)
    mu_ref = float(np.sum(spectrum.weights * mu_w))
    # Beyond the table: extend linearly with the last slope (p is monotonic in L).
    slope = (p[-1] - p[-2]) / (lengths[-1] - lengths[-2])
    # Below zero (noise on air rays) the map is the identity (p ≈ μ_ref L for thin water).
    p_ext = np.concatenate([[-10.0], p, [p[-1] + slope * 1000.0]])
    l_ext = np.concatenate([[-10.0 / mu_ref], lengths, [lengths[-1] + 1000.0]])
    return WaterCorrection(
        p_table=p_ext.astype(np.float32),
        corrected_table=(mu_ref * l_ext).astype(np.float32),
        mu_ref_per_mm=mu_ref,
    )
