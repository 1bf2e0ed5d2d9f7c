"""Geometry rules of :mod:`registration.dicom.geometry`, one test per rule function, on in-memory headers.

``test_dicom_series.py`` beside this file checks the same refusals end to end on real files; these pin
each ``check_*`` function on its own: it passes a good stack, and refuses the one broken property
with its error class, naming the offending file(s).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from registration.dicom import geometry as g
from registration.dicom.errors import (
    DuplicatePositionError,
    GantryTiltError,
    InconsistentImageSizeError,
    MissingGeometryError,
    MissingSliceError,
    MixedFrameOfReferenceError,
    MixedOrientationError,
    SingleSliceError,
    UnevenSpacingError,
)
from tests.helpers.dicom_factory import slice_header, slice_stack

UID = "1.2.3.4"


def _at(zs: list[float], **overrides: object) -> list[object]:
    return [slice_header(k, position_mm=(-10.0, -20.0, z), **overrides) for k, z in enumerate(zs)]


def _stack(zs: list[float]) -> g.SortedStack:
    return g.sort_along_normal(_at(zs))  # type: ignore[arg-type]


def test_check_required_geometry_accepts_good_and_names_every_problem() -> None:
    g.check_required_geometry(slice_stack(), UID)
    bad = slice_stack(
        overrides={
            1: {"position_mm": None},
            2: {"pixel_spacing_mm": (0.5, 0.0)},
            3: {"orientation": (1.0, 0.0, 0.0, 0.0, 0.9, 0.0)},
            4: {"samples_per_pixel": 3},
        }
    )
    with pytest.raises(MissingGeometryError) as err:
        g.check_required_geometry(bad, UID)
    msg = str(err.value)
    assert "ImagePositionPatient" in msg and "PixelSpacing" in msg and "SamplesPerPixel 3" in msg
    assert "not two orthogonal unit vectors" in msg
    assert set(err.value.files) == {Path(f"/series/IM{k:04d}.dcm") for k in (1, 2, 3, 4)}


def test_check_slice_count_refuses_one_slice() -> None:
    g.check_slice_count(slice_stack(2), UID)
    with pytest.raises(SingleSliceError, match="only 1 slice"):
        g.check_slice_count(slice_stack(1), UID)


def test_check_frame_of_reference_names_the_minority() -> None:
    g.check_frame_of_reference(slice_stack(), UID)
    with pytest.raises(MixedFrameOfReferenceError) as err:
        g.check_frame_of_reference(slice_stack(overrides={2: {"frame_of_reference_uid": "9.9"}}), UID)
    assert err.value.files == (Path("/series/IM0002.dcm"),)


def test_check_image_size_refuses_other_rows() -> None:
    g.check_image_size(slice_stack(), UID)
    with pytest.raises(InconsistentImageSizeError, match="Rows x Columns") as err:
        g.check_image_size(slice_stack(overrides={5: {"rows": 8}}), UID)
    assert err.value.files == (Path("/series/IM0005.dcm"),)


def test_check_pixel_spacing_tolerance_is_inclusive_of_rounding() -> None:
    tiny = g.PIXEL_SPACING_TOLERANCE_MM / 2
    g.check_pixel_spacing(slice_stack(overrides={1: {"pixel_spacing_mm": (0.5 + tiny, 0.5)}}), UID)
    with pytest.raises(InconsistentImageSizeError, match="PixelSpacing"):
        g.check_pixel_spacing(slice_stack(overrides={1: {"pixel_spacing_mm": (0.5001, 0.5)}}), UID)


def test_check_orientation_refuses_a_tilted_slice() -> None:
    c, s = math.cos(0.01), math.sin(0.01)
    g.check_orientation(slice_stack(), UID)
    with pytest.raises(MixedOrientationError) as err:
        g.check_orientation(slice_stack(overrides={3: {"orientation": (c, s, 0.0, -s, c, 0.0)}}), UID)
    assert err.value.files == (Path("/series/IM0003.dcm"),)


def test_sort_along_normal_ignores_file_and_instance_order() -> None:
    stack = _stack([2.4, 0.0, 1.6, 0.8])
    np.testing.assert_allclose(stack.s_mm, [0.0, 0.8, 1.6, 2.4])
    assert [h.path.name for h in stack.slices] == ["IM0001.dcm", "IM0003.dcm", "IM0002.dcm", "IM0000.dcm"]
    np.testing.assert_allclose(stack.normal, [0.0, 0.0, 1.0])


def test_check_no_duplicates_says_copied_file_for_same_uid() -> None:
    g.check_no_duplicates(_stack([0.0, 0.8, 1.6]), UID)
    copies = [slice_header(0), slice_header(0, path=Path("/series/copy.dcm")), slice_header(1)]
    with pytest.raises(DuplicatePositionError, match="a copied file") as err:
        g.check_no_duplicates(g.sort_along_normal(copies), UID)
    assert Path("/series/copy.dcm") in err.value.files


def test_check_no_shear_reports_the_tilt() -> None:
    g.check_no_shear(_stack([0.0, 0.8, 1.6]), UID)
    sheared = [slice_header(k, position_mm=(-10.0, -20.0 + 0.05 * k, 0.8 * k)) for k in range(3)]
    with pytest.raises(GantryTiltError, match=r"0\.100 mm sideways") as err:
        g.check_no_shear(g.sort_along_normal(sheared), UID)
    assert err.value.files == (Path("/series/IM0000.dcm"), Path("/series/IM0002.dcm"))


def test_check_no_missing_slices_counts_the_gap() -> None:
    g.check_no_missing_slices(_stack([0.0, 0.8, 1.6]), 0.8, 0.01, UID)
    with pytest.raises(MissingSliceError, match="2 missing between"):
        g.check_no_missing_slices(_stack([0.0, 0.8, 3.2, 4.0]), 0.8, 0.01, UID)


def test_check_even_steps_refuses_one_odd_step() -> None:
    g.check_even_steps(_stack([0.0, 0.8, 1.605]), 0.8, 0.01, UID)
    with pytest.raises(UnevenSpacingError, match=r"1\.0000 mm"):
        g.check_even_steps(_stack([0.0, 0.8, 1.8, 2.6]), 0.8, 0.01, UID)


def test_check_uniform_grid_refuses_drift_and_returns_the_spacing() -> None:
    assert g.check_uniform_grid(_stack([0.0, 0.8, 1.6, 2.4]), 0.01, UID) == pytest.approx(0.8)
    drifting = [0.0, 0.809, 1.618, 2.427, 3.218, 4.009, 4.8]  # every step within 0.01 of 0.8, s[3] is not
    with pytest.raises(UnevenSpacingError, match="off the uniform grid"):
        g.check_uniform_grid(_stack(drifting), 0.01, UID)


def test_spacing_tolerance_has_a_floor() -> None:
    assert g.spacing_tolerance_mm(0.833) == pytest.approx(g.SPACING_TOLERANCE_MIN_MM)
    assert g.spacing_tolerance_mm(5.0) == pytest.approx(0.05)


def test_image_from_voxel_known_answer_for_anisotropic_pixels() -> None:
    stack = _stack([30.0, 30.8, 31.6])
    affine = g.image_from_voxel(stack, (0.6, 0.4))
    expected = np.array(
        [[0.4, 0.0, 0.0, -10.0], [0.0, 0.6, 0.0, -20.0], [0.0, 0.0, 0.8, 30.0], [0.0, 0.0, 0.0, 1.0]]
    )
    np.testing.assert_allclose(affine, expected, atol=1e-12)


def test_check_series_geometry_runs_the_rules_in_order() -> None:
    # both a missing position (rule 1) and a single slice (rule 2): rule 1 is reported
    with pytest.raises(MissingGeometryError):
        g.check_series_geometry([slice_header(0, position_mm=None)], UID)
    geometry = g.check_series_geometry(list(reversed(slice_stack(4))), UID)
    assert geometry.slice_spacing_mm == pytest.approx(0.8)
    assert [h.instance_number for h in geometry.slices] == [1, 2, 3, 4]
