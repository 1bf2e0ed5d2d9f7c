"""Phantom model: geometry, validation rules, symmetry margin (issue #2 item 2, #4 item 1)."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest

from registration.errors import PhantomDefinitionError
from registration.model.phantom import load_phantom, phantom_from_dict


def _base(phantom_path: Path) -> dict:
    return tomllib.loads(phantom_path.read_text())


def test_default_phantom_geometry(phantom) -> None:
    assert len(phantom.hole_ids) == 64
    assert 24 <= phantom.n_spheres <= 32
    # every hole centre 1.25 mm below its face, on a 15 mm grid
    h = phantom.holes_phantom_mm
    lateral = np.max(np.abs(h[:, :2]), axis=1)
    np.testing.assert_allclose(lateral, 35.0 - 1.25)
    assert set(np.round(h[:, 2], 6)) == {-22.5, -7.5, 7.5, 22.5}


def test_default_phantom_has_seven_symmetries_and_margin(phantom) -> None:
    margins = phantom.symmetry_margins()
    assert len(margins) == 7
    assert all(m >= 6 for _, m in margins)


def test_full_grid_has_margin_zero(phantom_path: Path) -> None:
    d = _base(phantom_path)
    ph0 = load_phantom(phantom_path)
    d["filled"] = list(ph0.hole_ids)
    d["min_symmetry_margin"] = 0
    full = phantom_from_dict(d)
    assert full.symmetry_margin == 0


def test_symmetric_pattern_refused_names_rotation(phantom_path: Path) -> None:
    d = _base(phantom_path)
    d["filled"] = list(load_phantom(phantom_path).hole_ids)
    with pytest.raises(PhantomDefinitionError, match=r"ambiguous under the rotation .*fill"):
        phantom_from_dict(d)


def test_duplicate_holes_refused(phantom_path: Path) -> None:
    d = _base(phantom_path)
    d["filled"] = [*d["filled"], d["filled"][0]]
    with pytest.raises(PhantomDefinitionError, match="listed twice"):
        phantom_from_dict(d)


def test_unknown_hole_refused(phantom_path: Path) -> None:
    d = _base(phantom_path)
    d["filled"] = [*d["filled"], "+z-r0c0"]
    with pytest.raises(PhantomDefinitionError, match="unknown hole ids"):
        phantom_from_dict(d)


def test_sphere_outside_cube_refused(phantom_path: Path) -> None:
    d = _base(phantom_path)
    d["hole_centre_depth_mm"] = 0.5  # sphere of radius 1.25 would stick out by 0.75 mm
    with pytest.raises(PhantomDefinitionError, match="stick out"):
        phantom_from_dict(d)


def test_wrong_units_refused(phantom_path: Path) -> None:
    d = _base(phantom_path)
    d["units"] = "m"
    with pytest.raises(PhantomDefinitionError, match="units must be 'mm'"):
        phantom_from_dict(d)


def test_metre_values_refused(phantom_path: Path) -> None:
    d = _base(phantom_path)
    d["cube_size_mm"] = [70000.0, 70000.0, 80000.0]
    with pytest.raises(PhantomDefinitionError, match="in mm"):
        phantom_from_dict(d)


def test_missing_file_and_bad_toml(tmp_path: Path) -> None:
    with pytest.raises(PhantomDefinitionError, match="not found"):
        load_phantom(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("name = [unclosed")
    with pytest.raises(PhantomDefinitionError, match="not valid TOML"):
        load_phantom(bad)


def test_sphere_material_defaults_to_steel(phantom) -> None:
    assert phantom.sphere_material == "steel"


def test_tungsten_carbide_rows_phantom() -> None:
    """40 WC spheres with rows of 3–4 neighbours at 15 mm pitch, still unambiguous (margin >= 6)."""
    from tests.helpers.paths import CONFIGS

    ph = load_phantom(CONFIGS / "phantoms" / "wc_rows40.toml")
    assert ph.sphere_material == "tungsten_carbide" and ph.n_spheres == 40
    assert ph.symmetry_margin >= ph.min_symmetry_margin >= 6
    filled = set(ph.filled_ids)
    for face in ("+x", "+y", "-x", "-y"):
        runs = sorted(_longest_run([f"{face}-r{r}c{c}" in filled for c in range(4)]) for r in range(4))
        assert runs[-1] == 4 and runs[-2] >= 3, f"face {face}: longest filled run per row {runs}"


def _longest_run(flags: list[bool]) -> int:
    best = cur = 0
    for f in flags:
        cur = cur + 1 if f else 0
        best = max(best, cur)
    return best


def test_unknown_sphere_material_refused(phantom_path: Path) -> None:
    d = _base(phantom_path)
    d["sphere_material"] = "gold"
    with pytest.raises(PhantomDefinitionError, match="sphere_material 'gold'"):
        phantom_from_dict(d)
