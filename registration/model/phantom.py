"""The calibration phantom: hole grid, filled spheres, symmetry margin.

The Bai et al. 2018 phantom (doi:10.1088/1742-6596/1016/1/012006, §2.1) is a
70 × 70 × 80 mm plastic cube whose four side faces each carry a 4 × 4 grid of
Ø2.5 mm holes at 15 mm pitch; a metal sphere sits in each filled hole with its
centre 1.25 mm below the face.  Phantom frame: origin at the cube centre, x and
y along the 70 mm edges, z along the 80 mm edge (design.md §3).

The full grid maps onto itself under 8 proper rotations (design.md §4), so a
usable phantom fills an asymmetric subset of holes.  :func:`symmetry_margins`
counts, for each non-trivial symmetry of the hole grid, how many filled spheres
land on empty holes; :func:`load_phantom` refuses a pattern whose smallest
margin is below ``min_symmetry_margin``.
"""

from __future__ import annotations

import functools
import itertools
import os
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from registration.errors import PhantomDefinitionError
from registration.model.frames import rotation_angle_deg

FACES = ("+x", "+y", "-x", "-y")
"""Side faces in hole-index order; outward normals."""

_NORMALS = {"+x": (1.0, 0.0, 0.0), "+y": (0.0, 1.0, 0.0), "-x": (-1.0, 0.0, 0.0), "-y": (0.0, -1.0, 0.0)}

SPHERE_MATERIALS = ("steel", "tungsten_carbide", "titanium")
"""Sphere materials the simulator models (mocks/oarm/physics.py); ``steel`` when the file says none."""

SYMMETRY_MATCH_TOL_MM = 1e-6
"""Two hole centres coincide under a symmetry when closer than this (exact grid arithmetic)."""


@dataclass(frozen=True, eq=False)
class Symmetry:
    """A proper rotation (about the phantom origin) mapping the hole grid onto itself."""

    rotation: NDArray[np.float64]  # (3, 3)
    hole_permutation: NDArray[np.int64]  # (n_holes,) hole index → image hole index

    @property
    def angle_deg(self) -> float:
        return rotation_angle_deg(self.rotation)

    def describe(self) -> str:
        r = self.rotation
        skew = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
        if np.linalg.norm(skew) > 1e-9:  # angle < 180°: the skew part gives axis and sense
            axis = skew / np.linalg.norm(skew)
        else:  # 180°: axis is the eigenvector of eigenvalue +1, sense irrelevant
            w, v = np.linalg.eig(r)
            axis = np.real(v[:, int(np.argmin(np.abs(w - 1.0)))])
            axis = axis / np.linalg.norm(axis)
            axis = axis * np.sign(axis[np.argmax(np.abs(axis))])
        return f"{self.angle_deg:.0f}° about ({axis[0]:+.3f}, {axis[1]:+.3f}, {axis[2]:+.3f})"


@dataclass(frozen=True, eq=False)
class Phantom:
    """A phantom definition, validated on construction by :func:`load_phantom`.

    Attributes
    ----------
    name : str
    size_mm : ndarray, shape (3,)
        Cube edge lengths along phantom x, y, z.
    sphere_diameter_mm : float
    hole_ids : tuple of str
        Every hole, e.g. ``"+x-r0c3"`` (face, row from −z, column along
        z × normal).
    holes_phantom_mm : ndarray, shape (n_holes, 3)
        Hole (sphere) centres in the phantom frame.
    filled : ndarray of bool, shape (n_holes,)
    min_symmetry_margin : int
    sphere_material : str
        One of :data:`SPHERE_MATERIALS` (optional key ``sphere_material``; default ``steel``).
    """

    name: str
    size_mm: NDArray[np.float64]
    sphere_diameter_mm: float
    hole_pitch_mm: float
    hole_ids: tuple[str, ...]
    holes_phantom_mm: NDArray[np.float64]
    filled: NDArray[np.bool_]
    min_symmetry_margin: int
    sphere_material: str = "steel"

    @property
    def sphere_radius_mm(self) -> float:
        return self.sphere_diameter_mm / 2.0

    @property
    def filled_indices(self) -> NDArray[np.int64]:
        return np.flatnonzero(self.filled).astype(np.int64)

    @property
    def filled_ids(self) -> tuple[str, ...]:
        return tuple(self.hole_ids[i] for i in self.filled_indices)

    @property
    def centres_phantom_mm(self) -> NDArray[np.float64]:
        """(N, 3) centres of the filled spheres in the phantom frame, in the phantom's sphere order."""
        return np.asarray(self.holes_phantom_mm[self.filled], dtype=np.float64)

    @property
    def hole_axes_phantom(self) -> NDArray[np.float64]:
        """(n_holes, 3) outward unit axis of every hole (its face's normal), phantom frame."""
        return np.asarray([_NORMALS[h.split("-r")[0]] for h in self.hole_ids], dtype=np.float64)

    @property
    def axes_phantom(self) -> NDArray[np.float64]:
        """(N, 3) outward unit axes of the filled holes, in the phantom's sphere order."""
        return np.asarray(self.hole_axes_phantom[self.filled], dtype=np.float64)

    @property
    def n_spheres(self) -> int:
        return int(self.filled.sum())

    @functools.cached_property
    def _symmetries(self) -> tuple[Symmetry, ...]:
        return tuple(grid_symmetries(self.holes_phantom_mm))

    def symmetries(self) -> list[Symmetry]:
        """Non-trivial proper rotations mapping the hole grid onto itself (computed once)."""
        return list(self._symmetries)

    def symmetry_margins(self) -> list[tuple[Symmetry, int]]:
        """For each non-trivial symmetry, how many filled spheres land on empty holes."""
        return symmetry_margins(self.filled, self.symmetries())

    @property
    def symmetry_margin(self) -> int:
        """Smallest margin over the non-trivial symmetries (n_spheres if there are none)."""
        margins = [m for _, m in self.symmetry_margins()]
        return min(margins) if margins else self.n_spheres


def _proper_axis_rotations() -> list[NDArray[np.float64]]:
    """The 24 proper rotations of a cube (signed permutation matrices with det +1)."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            m = np.zeros((3, 3))
            for row, (col, s) in enumerate(zip(perm, signs, strict=True)):
                m[row, col] = s
            if np.linalg.det(m) > 0:
                out.append(m)
    return out


def grid_symmetries(holes_mm: NDArray[np.float64]) -> list[Symmetry]:
    """Non-trivial cube rotations that map the set of hole centres onto itself."""
    syms = []
    for r in _proper_axis_rotations():
        if np.allclose(r, np.eye(3)):
            continue
        mapped = holes_mm @ r.T
        d = np.linalg.norm(mapped[:, None, :] - holes_mm[None, :, :], axis=2)
        nearest = np.argmin(d, axis=1)
        if np.all(d[np.arange(len(holes_mm)), nearest] < SYMMETRY_MATCH_TOL_MM):
            syms.append(Symmetry(rotation=r, hole_permutation=nearest.astype(np.int64)))
    return syms


def symmetry_margins(filled: NDArray[np.bool_], syms: list[Symmetry]) -> list[tuple[Symmetry, int]]:
    """Filled spheres that a symmetry sends onto empty holes, per symmetry."""
    out = []
    for s in syms:
        images = s.hole_permutation[filled]
        out.append((s, int(np.count_nonzero(~filled[images]))))
    return out


def make_grid_holes(
    size_mm: NDArray[np.float64], pitch_mm: float, grid: tuple[int, int], depth_mm: float
) -> tuple[tuple[str, ...], NDArray[np.float64]]:
    """Hole ids and centres for a grid on each of the four side faces."""
    n_rows, n_cols = grid
    ids: list[str] = []
    pts: list[NDArray[np.float64]] = []
    half = np.asarray(size_mm, dtype=np.float64) / 2.0
    z_axis = np.array([0.0, 0.0, 1.0])
    for face in FACES:
        n = np.array(_NORMALS[face])
        u = np.cross(z_axis, n)
        face_offset = float(half[0] if face[1] == "x" else half[1]) - depth_mm
        for row in range(n_rows):
            zc = (row - (n_rows - 1) / 2.0) * pitch_mm
            for col in range(n_cols):
                uc = (col - (n_cols - 1) / 2.0) * pitch_mm
                ids.append(f"{face}-r{row}c{col}")
                pts.append(n * face_offset + u * uc + z_axis * zc)
    return tuple(ids), np.asarray(pts, dtype=np.float64)


def _require(d: dict[str, Any], key: str, path: Path) -> Any:
    if key not in d:
        raise PhantomDefinitionError(f"{path}: missing key '{key}'")
    return d[key]


def load_phantom(path: str | Path) -> Phantom:
    """Load and validate a phantom TOML file (see ``configs/phantoms/bai2018_cube.toml``).

    Raises
    ------
    PhantomDefinitionError
        Unreadable TOML, wrong units, duplicate or unknown hole ids, spheres
        sticking out of the cube, or a filled pattern whose symmetry margin is
        below ``min_symmetry_margin`` (the message names the rotation and the
        holes to fill).
    """
    from registration.dicom.errors import NotRegularFileError
    from registration.dicom.files import kind_of, open_regular

    p = Path(path)
    if not os.path.lexists(p):
        raise PhantomDefinitionError(f"phantom file not found: {p}")
    try:
        with open_regular(p) as f:  # stat before open, O_NONBLOCK: a FIFO or device is never read
            text = f.read().decode("utf-8")
        d = tomllib.loads(text)
    except NotRegularFileError as e:
        kind = kind_of(os.stat(p).st_mode) if p.exists() else "a dangling or looping link"
        raise PhantomDefinitionError(
            f"phantom file {p} is {kind}, not a regular file: not read; point it at the phantom's TOML file"
        ) from e
    except OSError as e:
        raise PhantomDefinitionError(f"cannot read phantom file {p}: {e.strerror or e}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise PhantomDefinitionError(f"{p}: not valid TOML: {e}") from None
    return phantom_from_dict(d, source=p)


def phantom_from_dict(d: dict[str, Any], source: Path | str = "<phantom>") -> Phantom:
    """Build and validate a :class:`Phantom` from the parsed TOML mapping."""
    src = Path(str(source))
    units = d.get("units", "mm")
    if units != "mm":
        raise PhantomDefinitionError(f"{src}: units must be 'mm', found {units!r}")
    try:
        size_mm = np.asarray(_require(d, "cube_size_mm", src), dtype=np.float64).reshape(3)
        diameter = float(_require(d, "sphere_diameter_mm", src))
        pitch = float(_require(d, "hole_pitch_mm", src))
        depth = float(_require(d, "hole_centre_depth_mm", src))
        grid_raw = _require(d, "grid_rows_cols", src)
        grid = (int(grid_raw[0]), int(grid_raw[1]))
        min_margin = int(d.get("min_symmetry_margin", 0))
        material = str(d.get("sphere_material", "steel"))
    except (TypeError, ValueError, IndexError) as e:
        raise PhantomDefinitionError(f"{src}: malformed geometry value: {e}") from None
    if np.any(size_mm <= 0) or diameter <= 0 or pitch <= 0 or depth < 0:
        raise PhantomDefinitionError(f"{src}: sizes must be positive (mm)")
    if size_mm.max() > 1000 or diameter > 50:
        raise PhantomDefinitionError(
            f"{src}: cube {size_mm.tolist()} mm / sphere {diameter} mm is implausible; are the values in mm?"
        )
    if material not in SPHERE_MATERIALS:
        raise PhantomDefinitionError(
            f"{src}: sphere_material {material!r} is not one of {list(SPHERE_MATERIALS)}"
        )
    ids, holes = make_grid_holes(size_mm, pitch, grid, depth)
    r = diameter / 2.0
    outside = np.any(np.abs(holes) + r > size_mm / 2.0 + 1e-9, axis=1)
    if np.any(outside):
        bad = [ids[i] for i in np.flatnonzero(outside)]
        raise PhantomDefinitionError(
            f"{src}: spheres {bad[:5]} stick out of the {size_mm.tolist()} mm cube; "
            "check hole_centre_depth_mm, hole_pitch_mm and grid_rows_cols"
        )
    filled_ids = list(_require(d, "filled", src))
    seen: set[str] = set()
    dups = [h for h in filled_ids if h in seen or seen.add(h)]  # type: ignore[func-returns-value]
    if dups:
        raise PhantomDefinitionError(f"{src}: holes listed twice in 'filled': {sorted(set(dups))}")
    index = {h: i for i, h in enumerate(ids)}
    unknown = [h for h in filled_ids if h not in index]
    if unknown:
        raise PhantomDefinitionError(
            f"{src}: unknown hole ids {unknown[:5]}; ids look like '+x-r0c3' (face +x/+y/-x/-y, "
            f"row 0..{grid[0] - 1} from −z, column 0..{grid[1] - 1})"
        )
    if len(filled_ids) < 4:
        raise PhantomDefinitionError(f"{src}: at least 4 filled holes are needed, found {len(filled_ids)}")
    filled = np.zeros(len(ids), dtype=bool)
    filled[[index[h] for h in filled_ids]] = True
    ph = Phantom(
        name=str(d.get("name", src.stem)),
        size_mm=size_mm,
        sphere_diameter_mm=diameter,
        hole_pitch_mm=pitch,
        hole_ids=ids,
        holes_phantom_mm=holes,
        filled=filled,
        min_symmetry_margin=min_margin,
        sphere_material=material,
    )
    check_symmetry_margin(ph, src)
    return ph


def check_symmetry_margin(ph: Phantom, source: Path | str = "<phantom>") -> None:
    """Refuse a filled pattern whose margin is below ``ph.min_symmetry_margin``."""
    for sym, margin in ph.symmetry_margins():
        if margin < ph.min_symmetry_margin:
            # Suggest empty holes whose image under this symmetry is also empty:
            # filling one adds a sphere that lands on an empty hole.
            sugg = [
                ph.hole_ids[i] for i in np.flatnonzero(~ph.filled) if not ph.filled[sym.hole_permutation[i]]
            ]
            raise PhantomDefinitionError(
                f"{source}: filled pattern is ambiguous under the rotation {sym.describe()}: only "
                f"{margin} filled sphere(s) land on empty holes, min_symmetry_margin is "
                f"{ph.min_symmetry_margin}; fill {ph.min_symmetry_margin - margin} more of {sugg[:8]} "
                "(or empty holes that the rotation maps onto filled ones)"
            )
