"""Finding files, grouping them by series and choosing the series to load (folder or DICOMDIR).

1. **Find files.**  A folder is walked recursively; a ``DICOMDIR`` (or a folder
   holding one at its root) is read as a File-set with
   :class:`pydicom.fileset.FileSet`.
2. **Read headers** (:mod:`registration.dicom.headers`).
3. **Group** by SeriesInstanceUID (0020,000E) and **pick** the series: the one
   named by UID, else the largest consistent (axial first) stack.
"""

from __future__ import annotations

import logging
import os
import stat
from collections import Counter, defaultdict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydicom import dcmread

from registration.dicom.errors import (
    AmbiguousSeriesError,
    NoCtSeriesError,
    NotRegularFileError,
    SeriesError,
    SeriesNotFoundError,
)
from registration.dicom.files import kind_of, regular_file_problem
from registration.dicom.geometry import SeriesGeometry, check_series_geometry, is_axial
from registration.dicom.headers import (
    CT_IMAGE_STORAGE,
    ENHANCED_CT_IMAGE_STORAGE,
    SkippedFile,
    SliceHeader,
    read_headers,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SeriesSummary:
    """Header-only description of one CT series (what the folder watcher needs).

    Attributes
    ----------
    series_uid, frame_of_reference_uid, study_uid : str
        (0020,000E), (0020,0052) (the first slice's if mixed), (0020,000D).
    modality, series_description : str
    n_files : int
        Files that belong to the series (after skipping junk).
    n_slices : int
        Frames (= files for single-frame CT).
    rows, columns : int
        Most common Rows / Columns.
    pixel_spacing_mm : tuple of 2 float or None
        (row spacing, column spacing) of the first slice.
    orientation : tuple of 6 float or None
        ImageOrientationPatient of the first slice.
    slice_spacing_mm : float or None
        From the sorted positions, ``None`` unless consistent.
    first_position_mm, last_position_mm : tuple of 3 float or None
        IPP (LPS, mm) of the first and last slice along the normal, ``None`` unless consistent.
    is_axial : bool
        Slice normal within 45° of the patient z axis.
    problem : str
        ``""`` when the series is loadable, else the refusal message :func:`load_series` would raise.
    problem_type : str
        The refusal's exception class name, ``""`` when loadable.
    files : tuple of Path
        In slice order when consistent, else in path order.
    """

    series_uid: str
    frame_of_reference_uid: str
    study_uid: str
    modality: str
    series_description: str
    n_files: int
    n_slices: int
    rows: int
    columns: int
    pixel_spacing_mm: tuple[float, ...] | None
    orientation: tuple[float, ...] | None
    slice_spacing_mm: float | None
    first_position_mm: tuple[float, ...] | None
    last_position_mm: tuple[float, ...] | None
    is_axial: bool
    problem: str
    problem_type: str
    files: tuple[Path, ...]

    @property
    def consistent(self) -> bool:
        """True when :func:`load_series` would accept this series."""
        return not self.problem


@dataclass(frozen=True)
class FolderScan:
    """Result of the header pass over a folder / file-set: every CT series and every skipped file."""

    root: Path
    series: tuple[SeriesSummary, ...]
    skipped: tuple[SkippedFile, ...]


def scan_folder(root: Path) -> tuple[list[SliceHeader], list[SkippedFile]]:
    """Header pass over every candidate file under ``root``; refused paths are skipped files."""
    paths, skipped = _candidate_files(root)
    headers: list[SliceHeader] = []
    memo: dict[tuple[Any, ...], Any] = {}
    for p in paths:
        result = read_headers(p, memo)
        if isinstance(result, SkippedFile):
            skipped.append(result)
        else:
            headers.extend(result)
    return headers, skipped


def _root_kind(root: Path) -> str:
    """``"dir"``, ``"file"`` (regular), or raise the refusal for anything else (never opened)."""
    try:
        st = os.stat(root)
    except FileNotFoundError:
        raise NoCtSeriesError(
            f"{root}: no such file or folder; expected a folder of DICOM files or a DICOMDIR.",
            files=[root],
        ) from None
    except OSError as exc:
        raise NotRegularFileError(
            f"{root}: cannot be examined ({type(exc).__name__}: {exc.strerror}); expected a folder of DICOM "
            "files or a DICOMDIR.",
            files=[root],
        ) from None
    if stat.S_ISDIR(st.st_mode):
        return "dir"
    if stat.S_ISREG(st.st_mode):
        return "file"
    raise NotRegularFileError(
        f"{root}: {kind_of(st.st_mode)}, neither a folder nor a regular file; never opened. Point the "
        "loader at the O-arm export folder (or its DICOMDIR).",
        files=[root],
    )


def _candidate_files(root: Path) -> tuple[list[Path], list[SkippedFile]]:
    """Files to look at (the File-set's instances when there is a DICOMDIR, else every regular file
    under ``root``) and the paths refused without opening them (FIFOs, devices, link loops, links or
    DICOMDIR references leaving the folder: :mod:`registration.dicom.files`)."""
    if _root_kind(root) == "file":
        if root.name.upper() == "DICOMDIR":
            return _checked(_fileset_files(root), root.parent)
        return [root], []
    dicomdir = next(
        (p for p in root.iterdir() if p.name.upper() == "DICOMDIR" and not regular_file_problem(p, root)),
        None,
    )
    if dicomdir is not None:
        return _checked(_fileset_files(dicomdir), root)
    out: list[Path] = []
    for dirpath, dirnames, filenames in os.walk(root):  # never follows links to folders
        dirnames[:] = sorted(d for d in dirnames if not _not_scan_folder(Path(dirpath) / d))
        out.extend(Path(dirpath) / f for f in sorted(filenames))
    return _checked(out, root)


SKIPPED_FOLDER_NAMES = frozenset({"__pycache__", "node_modules", "site-packages", "dist-packages"})
"""Folders under a scan root that are never a scan export (software trees hold test DICOM files)."""


def _not_scan_folder(folder: Path) -> bool:
    """A folder the walk skips: hidden (``.venv``, ``.git``, ``.cache``), a virtual
    environment (holds ``pyvenv.cfg``) or a package tree (:data:`SKIPPED_FOLDER_NAMES`).  The root
    itself is always searched: a user who points at a hidden folder means it."""
    if folder.name.startswith(".") or folder.name in SKIPPED_FOLDER_NAMES:
        log.debug("not searching %s for DICOM (hidden or software folder)", folder)
        return True
    if (folder / "pyvenv.cfg").is_file():
        log.debug("not searching %s for DICOM (a virtual environment)", folder)
        return True
    return False


def _checked(paths: Sequence[Path], inside: Path) -> tuple[list[Path], list[SkippedFile]]:
    """Split ``paths`` into those safe to open and the refused ones (with the reason, logged)."""
    ok: list[Path] = []
    refused: list[SkippedFile] = []
    for p in paths:
        problem = regular_file_problem(p, inside)
        if problem:
            log.warning("skipping %s: %s", p, problem)
            refused.append(SkippedFile(path=p, reason=problem))
        else:
            ok.append(p)
    return ok, refused


def _fileset_files(dicomdir: Path) -> list[Path]:
    """Paths of every instance a DICOMDIR references (PS3.10 File-set)."""
    from pydicom.fileset import FileSet

    problem = regular_file_problem(dicomdir)
    if problem:
        raise NotRegularFileError(f"{dicomdir}: {problem}", files=[dicomdir])
    try:
        ds = dcmread(dicomdir)  # FileSet needs the dataset's filename (checked regular just above)
        fs = FileSet(ds)
        paths = [Path(instance.path) for instance in fs]
    except Exception as exc:  # pydicom raises many types for a damaged DICOMDIR
        raise NoCtSeriesError(
            f"{dicomdir}: cannot read the DICOMDIR file-set ({type(exc).__name__}: {exc}); "
            "point the loader at the folder of image files instead, or re-export the media.",
            files=[dicomdir],
        ) from exc
    log.info("DICOMDIR %s references %d instance(s)", dicomdir, len(paths))
    return paths


def group_by_series(headers: Sequence[SliceHeader]) -> dict[str, list[SliceHeader]]:
    groups: dict[str, list[SliceHeader]] = defaultdict(list)
    for h in headers:
        groups[h.series_uid].append(h)
    return dict(groups)


def summarise(uid: str, slices: Sequence[SliceHeader]) -> SeriesSummary:
    first = slices[0]
    files_by_name = tuple(sorted({h.path for h in slices}))
    rows, columns = Counter((h.rows, h.columns) for h in slices).most_common(1)[0][0]
    problem, problem_type = "", ""
    spacing: float | None = None
    first_pos: tuple[float, ...] | None = None
    last_pos: tuple[float, ...] | None = None
    files = files_by_name
    try:
        geometry = check_series_geometry(slices, uid)
    except SeriesError as exc:
        problem, problem_type = str(exc), type(exc).__name__
    else:
        spacing = geometry.slice_spacing_mm
        first_pos = geometry.slices[0].position_mm
        last_pos = geometry.slices[-1].position_mm
        files = tuple(dict.fromkeys(h.path for h in geometry.slices))
    return SeriesSummary(
        series_uid=uid,
        frame_of_reference_uid=first.frame_of_reference_uid,
        study_uid=first.study_uid,
        modality=first.modality,
        series_description=first.series_description,
        n_files=len(files_by_name),
        n_slices=len(slices),
        rows=rows,
        columns=columns,
        pixel_spacing_mm=first.pixel_spacing_mm,
        orientation=first.orientation,
        slice_spacing_mm=spacing,
        first_position_mm=first_pos,
        last_position_mm=last_pos,
        is_axial=is_axial(first.orientation),
        problem=problem,
        problem_type=problem_type,
        files=files,
    )


def _skipped_text(skipped: Sequence[SkippedFile], limit: int = 8) -> str:
    if not skipped:
        return "no files were skipped"
    shown = "; ".join(f"{s.path}: {s.reason}" for s in skipped[:limit])
    more = f" (+{len(skipped) - limit} more)" if len(skipped) > limit else ""
    return f"{len(skipped)} file(s) skipped: {shown}{more}"


def _checked_geometry(
    slices: Sequence[SliceHeader], series_uid: str, skipped: Sequence[SkippedFile]
) -> SeriesGeometry:
    """:func:`check_series_geometry`, naming this series' skipped files in a refusal (a truncated
    file of the series shows up as a missing slice; the user needs both facts)."""
    try:
        return check_series_geometry(slices, series_uid)
    except SeriesError as exc:
        lost = [sk for sk in skipped if sk.series_uid == series_uid]
        if not lost:
            raise
        raise type(exc)(
            f"{exc} Files of this series that could not be used: {_skipped_text(lost)}.",
            files=[*exc.files, *(sk.path for sk in lost)],
            series_uid=series_uid,
        ) from exc


def select_series(
    root: Path,
    groups: dict[str, list[SliceHeader]],
    skipped: Sequence[SkippedFile],
    series_uid: str | None,
    *,
    unique: bool = False,
) -> tuple[str, SeriesGeometry]:
    """Pick the series to load and return its checked geometry (raising the refusal otherwise).

    ``unique``: refuse (:class:`AmbiguousSeriesError`, naming every candidate) when more than one
    series is loadable and ``series_uid`` names none, instead of taking the largest stack.
    """
    if not groups:
        raise NoCtSeriesError(
            f"{root}: no CT image series found (CT Image Storage {CT_IMAGE_STORAGE} or Enhanced CT "
            f"{ENHANCED_CT_IMAGE_STORAGE}); {_skipped_text(skipped)}. Point the loader at the O-arm export "
            "folder (or its DICOMDIR) and check that the export finished.",
            files=[s.path for s in skipped],
        )
    if series_uid is not None:
        return series_uid, _named_series(root, groups, skipped, series_uid)
    good: list[tuple[str, SeriesGeometry]] = []
    bad: list[tuple[str, SeriesError]] = []
    for uid, hs in groups.items():
        try:
            good.append((uid, _checked_geometry(hs, uid, skipped)))
        except SeriesError as exc:
            bad.append((uid, exc))
    for uid, refused in bad:
        log.info("series %s is not loadable: %s", uid, refused)
    if not good:
        raise _none_loadable(root, groups, bad)
    if unique and len(good) > 1:
        names = "; ".join(f"{uid} ({len(g.slices)} slices, first {g.slices[0].path})" for uid, g in good)
        raise AmbiguousSeriesError(
            f"{root}: {len(good)} loadable CT series: {names}. Pass --series-uid UID to choose one, or "
            "point at the folder of that series alone.",
            files=[g.slices[0].path for _, g in good],
        )
    return _best_series(root, good)


def _named_series(
    root: Path, groups: dict[str, list[SliceHeader]], skipped: Sequence[SkippedFile], series_uid: str
) -> SeriesGeometry:
    """The checked geometry of the series the caller named, or :class:`SeriesNotFoundError`."""
    if series_uid not in groups:
        available = "; ".join(f"{uid} ({len({h.path for h in hs})} files)" for uid, hs in groups.items())
        lost = [s for s in skipped if s.series_uid == series_uid]
        extra = f"; its files were all skipped: {_skipped_text(lost)}" if lost else ""
        raise SeriesNotFoundError(
            f"{root}: no CT series with SeriesInstanceUID {series_uid}{extra}. Available CT series: "
            f"{available}. Pass one of these UIDs, or none to take the largest consistent stack.",
            files=[s.path for s in lost],
            series_uid=series_uid,
        )
    return _checked_geometry(groups[series_uid], series_uid, skipped)


def _none_loadable(
    root: Path, groups: dict[str, list[SliceHeader]], bad: Sequence[tuple[str, SeriesError]]
) -> SeriesError:
    """The refusal of the largest series, naming the other (also refused) series."""
    worst_uid, refusal = max(bad, key=lambda b: len(groups[b[0]]))
    if len(bad) == 1:
        return refusal
    others = "; ".join(f"{u} ({len(groups[u])} slices): {type(e).__name__}" for u, e in bad if u != worst_uid)
    combined = type(refusal)(
        f"{refusal} Other CT series under {root}, none loadable either: {others}.",
        files=refusal.files,
        series_uid=worst_uid,
    )
    combined.__cause__ = refusal
    return combined


def _best_series(root: Path, good: list[tuple[str, SeriesGeometry]]) -> tuple[str, SeriesGeometry]:
    """Axial stacks first, then the most slices; a tie is :class:`AmbiguousSeriesError`."""

    def rank(item: tuple[str, SeriesGeometry]) -> tuple[bool, int]:
        return (is_axial(item[1].slices[0].orientation), len(item[1].slices))

    good.sort(key=rank, reverse=True)
    best_uid, best = good[0]
    if len(good) > 1 and rank(good[1]) == rank(good[0]):
        tied = [uid for uid, g in good if rank((uid, g)) == rank(good[0])]
        raise AmbiguousSeriesError(
            f"{root}: {len(tied)} consistent CT series with {len(best.slices)} slices each: "
            f"{', '.join(tied)}. Cannot tell which one is the scan to register; pass the series UID "
            "explicitly.",
            files=[g.slices[0].path for _, g in good[: len(tied)]],
        )
    for uid, g in good[1:]:
        log.info("also found consistent series %s (%d slices), not loaded", uid, len(g.slices))
    return best_uid, best
