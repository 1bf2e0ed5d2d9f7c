"""Read and write the registration's JSON files.

* points file: ``{"spheres_mm": [[x, y, z], ...]}`` (robot frame in phantom sphere
  order, or image frame for ``--image-points``);
* targets file: ``{"targets_robot_mm": [[x, y, z], ...]}`` (robot frame; the API's
  ``targets_image_mm`` are image-frame LPS points: one frame per name);
* registration file: the ``oarmreg register --json`` output (``"image_from_robot"``
  4 × 4 nested list, …) or a refusal ``{"refused": true, "reason": …, "error": …}``.

Every problem raises :class:`~registration.errors.PointsFileError` naming the
file, what was expected and what was found; a file that cannot be read at all (missing, a folder,
no permission) raises :class:`~registration.errors.InputFileUnreadableError`.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any, Final

import numpy as np
from numpy.typing import ArrayLike

from registration.arrays import F64
from registration.errors import InputFileUnreadableError, NotRigidError, PointsFileError
from registration.model.frames import as_transform

MAX_ABS_COORD_MM: Final = 1.0e5
"""Coordinates beyond 100 m are not millimetres of an operating room."""


def read_json(path: str | Path) -> Any:
    p = Path(path)
    if p.exists() and not p.is_file() and not p.is_dir():
        raise InputFileUnreadableError(f"{p}: not a regular file (a device, pipe or socket); name a file")
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputFileUnreadableError(f"{p}: no such file; check the path (from {Path.cwd()})") from None
    except IsADirectoryError:
        raise InputFileUnreadableError(f"{p}: is a directory; name the JSON file inside it") from None
    except OSError as e:
        raise InputFileUnreadableError(
            f"{p}: cannot read ({e.strerror or e}); check it is readable by this user"
        ) from None
    except UnicodeDecodeError as e:
        raise PointsFileError(f"{p}: not UTF-8 text ({e.reason} at byte {e.start}); expected JSON") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise PointsFileError(f"{p}: not valid JSON (line {e.lineno}, column {e.colno}: {e.msg})") from None


def _points_from(obj: Any, key: str, path: Path, *, min_points: int) -> F64:
    if not isinstance(obj, dict):
        raise PointsFileError(
            f'{path}: expected a JSON object {{"{key}": [[x, y, z], ...]}}, found {type(obj).__name__}'
        )
    if key not in obj:
        raise PointsFileError(
            f'{path}: missing key "{key}" (found keys {sorted(obj)[:8]}); '
            f'expected {{"{key}": [[x, y, z], ...]}}'
        )
    raw = obj[key]
    if not isinstance(raw, list):
        raise PointsFileError(f'{path}: "{key}" must be a list of [x, y, z] triples in mm')
    for k, row in enumerate(raw):
        if (
            not isinstance(row, list)
            or len(row) != 3
            or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in row)
        ):
            raise PointsFileError(f'{path}: "{key}"[{k}] must be [x, y, z] (3 numbers in mm), found {row!r}')
    arr = np.asarray(raw, dtype=np.float64).reshape(-1, 3)
    if not np.all(np.isfinite(arr)):
        bad = np.flatnonzero(~np.all(np.isfinite(arr), axis=1))
        raise PointsFileError(f'{path}: "{key}" rows {bad[:5].tolist()} are not finite')
    if len(arr) and float(np.max(np.abs(arr))) > MAX_ABS_COORD_MM:
        raise PointsFileError(
            f'{path}: "{key}" has coordinates beyond {MAX_ABS_COORD_MM:g} mm; are the values in mm?'
        )
    if len(arr) < min_points:
        raise PointsFileError(f'{path}: "{key}" holds {len(arr)} point(s), at least {min_points} needed')
    return arr


def read_points(path: str | Path, *, min_points: int = 3) -> F64:
    """Read ``{"spheres_mm": [[x, y, z], ...]}``; returns (N, 3) float64 mm.

    A ``0.0``-extent (all points identical) or metre-scaled file (all points
    within 1 of the origin while more than 3 points are given) is refused.
    """
    p = Path(path)
    arr = _points_from(read_json(p), "spheres_mm", p, min_points=min_points)
    if len(arr) > 3:
        extent = float(np.max(np.ptp(arr, axis=0)))
        if extent == 0.0:
            raise PointsFileError(f"{p}: all {len(arr)} spheres have the same coordinates")
        if extent < 1.0:
            raise PointsFileError(
                f"{p}: the spheres span only {extent:.3g} mm; the file looks like metres, convert to mm"
            )
    return arr


def write_points(path: str | Path, points_mm: ArrayLike, **extra: Any) -> Path:
    """Write ``{"spheres_mm": ...}`` (plus ``extra`` keys) atomically."""
    pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    return write_json(path, {"spheres_mm": pts.tolist(), **extra})


def read_targets(path: str | Path) -> F64:
    """Read ``{"targets_robot_mm": [[x, y, z], ...]}``; returns (T, 3) float64 mm (robot frame).

    A file with the old key ``targets_mm`` (the same name meant image-frame points in
    ``POST /register``) is refused, naming the new key.
    """
    p = Path(path)
    obj = read_json(p)
    if isinstance(obj, dict) and "targets_mm" in obj and "targets_robot_mm" not in obj:
        raise PointsFileError(
            f'{p}: "targets_mm" was renamed "targets_robot_mm" (robot frame, mm); rename the key '
            '(image-frame LPS targets go to POST /register as "targets_image_mm")'
        )
    return _points_from(obj, "targets_robot_mm", p, min_points=1)


def write_targets(path: str | Path, targets_robot_mm: ArrayLike) -> Path:
    pts = np.asarray(targets_robot_mm, dtype=np.float64).reshape(-1, 3)
    return write_json(path, {"targets_robot_mm": pts.tolist()})


def read_registration(path: str | Path) -> F64:
    """``image_from_robot`` (4 × 4, checked rigid) from a registration JSON file.

    Raises
    ------
    PointsFileError
        Unreadable, a recorded refusal, missing key or not a rigid 4 × 4.
    """
    p = Path(path)
    obj = read_json(p)
    if not isinstance(obj, dict):
        raise PointsFileError(f"{p}: expected a registration JSON object, found {type(obj).__name__}")
    if obj.get("refused"):
        raise PointsFileError(
            f"{p}: records a refused registration ({obj.get('error', 'error')}: {obj.get('reason', '?')}); "
            "run `oarmreg register` again until it succeeds"
        )
    if "image_from_robot" not in obj:
        raise PointsFileError(f'{p}: missing key "image_from_robot" (a 4 × 4 nested list)')
    try:
        m = np.asarray(obj["image_from_robot"], dtype=np.float64)
    except (TypeError, ValueError):
        raise PointsFileError(f'{p}: "image_from_robot" must be a 4 × 4 nested list of numbers') from None
    try:
        return as_transform(m, f"{p}: image_from_robot")
    except NotRigidError as e:
        raise PointsFileError(str(e)) from None


def write_json(path: str | Path, obj: Any) -> Path:
    """Write ``obj`` as indented JSON via a temporary file and ``os.replace`` (never half-written)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".part", dir=p.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(obj, f, indent=2, allow_nan=False)
            f.write("\n")
        os.replace(tmp, p)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return p
