"""The service's stored records: frozen dataclasses, one definition each.

The stores (:mod:`service.store`) read and write them; the API models
(:mod:`service.http.api.models`) are built from them with
``Model.model_validate(record, from_attributes=True)``.  Lists of numbers are tuples
so a record is immutable; JSON columns are decoded into these types once, in the
store.

Units are in the names (mm, rad, s); timestamps are ISO 8601 UTC strings.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

if TYPE_CHECKING:
    from drivers.errors import RobotLinkError
    from registration.errors import OarmRegError

ScanStatus = Literal["receiving", "complete", "reopened", "replaced", "invalid"]
"""A scan's state (:mod:`service.intake.scan_lifecycle`, docs/safety.md "Scan lifecycle"); only ``complete``
can be registered, verified or calibrated with."""
RegistrationStatus = Literal["accepted", "refused", "retired", "withdrawn"]

Matrix4 = tuple[tuple[float, ...], ...]
"""4 × 4 row-major transform, mm."""

Points3 = tuple[tuple[float, float, float], ...]
"""(N, 3) points, mm."""

JSONDict = dict[str, Any]
"""A JSON object kept as such (provenance, timings): written and read back verbatim."""


def matrix4(rows: Sequence[Sequence[float]]) -> Matrix4:
    """A nested sequence (e.g. ``ndarray.tolist()``) as a :data:`Matrix4` of Python floats."""
    return tuple(tuple(float(v) for v in row) for row in rows)


def points3(rows: Sequence[Sequence[float]]) -> Points3:
    """A nested sequence of (x, y, z) as :data:`Points3` of Python floats."""
    return tuple((float(p[0]), float(p[1]), float(p[2])) for p in rows)


def floats(values: Sequence[float] | None) -> tuple[float, ...] | None:
    return None if values is None else tuple(float(v) for v in values)


# ---- scans ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class ScanGeometry:
    """Where the scan's voxels are: ``image_from_voxel`` maps (i, j, k, 1) to LPS mm."""

    image_from_voxel: Matrix4
    spacing_mm: tuple[float, ...]
    shape_kji: tuple[int, ...]

    def to_json(self) -> JSONDict:
        return {
            "image_from_voxel": [list(r) for r in self.image_from_voxel],
            "spacing_mm": list(self.spacing_mm),
            "shape_kji": list(self.shape_kji),
        }

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> ScanGeometry:
        return cls(
            image_from_voxel=matrix4(d["image_from_voxel"]),
            spacing_mm=tuple(float(v) for v in d.get("spacing_mm", ())),
            shape_kji=tuple(int(v) for v in d.get("shape_kji", ())),
        )


StillnessVerdict = Literal["still", "moved", "incomplete"]
"""Whether the robot stayed still over a scan's window (registration.model.stillness.VERDICTS,
docs/safety.md "Stillness and health"): ``still`` may be registered; ``moved`` refuses as moved;
``incomplete`` (the joint history does not cover the window) refuses as unknown."""

STILLNESS_VERDICTS: tuple[StillnessVerdict, ...] = ("still", "moved", "incomplete")


def stillness_verdict(value: str) -> StillnessVerdict:
    """``value`` as a :data:`StillnessVerdict`.

    Raises
    ------
    ValueError
        ``value`` is none of :data:`STILLNESS_VERDICTS` (a stillness model or a stored row this
        software does not know): refuse rather than guess.
    """
    for v in STILLNESS_VERDICTS:
        if value == v:
            return v
    raise ValueError(
        f"unknown stillness verdict {value!r}: expected one of {', '.join(STILLNESS_VERDICTS)}; "
        "the database or the stillness model is newer than this software: upgrade oarmreg"
    )


@dataclass(frozen=True)
class JointSnapshot:
    """The joints captured at a scan's arrival and the stillness verdict over the window before it.

    ``verdict`` is the one source of truth for the gate
    (:func:`service.registrations.scan_checks.check_capture`); ``stillness_reason`` is for people
    and is never parsed.  ``joints_rad`` is None when no joint sample was available (link down,
    pre-existing series).
    """

    link_url: str
    link_state: str
    window_s: float
    verdict: StillnessVerdict
    captured_at: str = ""
    link_reason: str = ""
    joints_rad: tuple[float, ...] | None = None
    joints_received_at: str | None = None
    max_deviation_rad: float | None = None
    covered_s: float | None = None
    n_samples: int = 0
    stillness_reason: str = ""

    @property
    def still(self) -> bool:
        """The verdict is ``still``."""
        return self.verdict == "still"


@dataclass(frozen=True)
class ScanRecord:
    """One DICOM series the watcher recorded (one row per SeriesInstanceUID)."""

    id: int
    series_uid: str
    folder: str
    status: ScanStatus
    arrived_at: str
    updated_at: str
    frame_of_reference_uid: str = ""
    n_files: int = 0
    n_slices: int = 0
    rows: int = 0
    columns: int = 0
    geometry: ScanGeometry | None = None
    reason: str = ""
    seen_count: int = 1
    snapshot: JointSnapshot | None = None


@dataclass(frozen=True)
class NewScan:
    """What the watcher's intake knows about a series when it records it (no id yet)."""

    series_uid: str
    folder: str
    status: ScanStatus
    reason: str = ""
    frame_of_reference_uid: str = ""
    n_files: int = 0
    n_slices: int = 0
    rows: int = 0
    columns: int = 0
    geometry: ScanGeometry | None = None
    snapshot: JointSnapshot | None = None
    arrived_at: str | None = None


# ---- registrations -------------------------------------------------------------------------


@dataclass(frozen=True)
class SphereMatch:
    """One matched sphere: phantom hole id, index into the robot list and the detections, residual."""

    sphere: str
    robot_index: int
    image_index: int
    residual_mm: float


@dataclass(frozen=True)
class DetectionSummary:
    method: str = ""
    n_rejected: int = 0
    timings_s: Mapping[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class RegistrationFigures:
    """The quality figures of an accepted registration (``figures_json``)."""

    fle_mm: float
    n_expected: int
    n_detected: int
    n_matched: int
    symmetry_margin: int
    rotation_det: float
    predicted_tre_mm: tuple[float, ...]
    targets_image_mm: Points3
    targets_source: str
    spheres: tuple[SphereMatch, ...]
    detection: DetectionSummary = DetectionSummary()
    provenance: JSONDict = field(default_factory=dict)
    timings_s: Mapping[str, float] = field(default_factory=dict)
    predicted_chain_error_mm: float | None = None
    """The robot chain's predicted error over the working volume (mm RMS) — the active
    calibration's posterior figure, or the nominal model's prior when none; None before this version."""
    chain_error_source: str = ""
    series_geometry: JSONDict | None = None
    """The scan's volume (:class:`registration.imaging.scan_geometry.SeriesGeometry`), for the
    pose planner."""
    face_offset_mm: float | None = None
    """The phantom's face offset β of this scan (mm, along every hole's outward axis; None when not
    fitted or before this version): :mod:`registration.matching.face_offset`."""
    face_offset_se_mm: float | None = None

    def to_json(self) -> JSONDict:
        return {
            "face_offset_mm": self.face_offset_mm,
            "face_offset_se_mm": self.face_offset_se_mm,
            "predicted_chain_error_mm": self.predicted_chain_error_mm,
            "chain_error_source": self.chain_error_source,
            "series_geometry": self.series_geometry,
            "fle_mm": self.fle_mm,
            "n_expected": self.n_expected,
            "n_detected": self.n_detected,
            "n_matched": self.n_matched,
            "symmetry_margin": self.symmetry_margin,
            "rotation_det": self.rotation_det,
            "predicted_tre_mm": list(self.predicted_tre_mm),
            "targets_image_mm": [list(p) for p in self.targets_image_mm],
            "targets_source": self.targets_source,
            "spheres": [vars(s) for s in self.spheres],
            "detection": {**vars(self.detection), "timings_s": dict(self.detection.timings_s)},
            "provenance": self.provenance,
            "timings_s": dict(self.timings_s),
        }

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> RegistrationFigures:
        det = d.get("detection") or {}
        return cls(
            fle_mm=float(d["fle_mm"]),
            n_expected=int(d["n_expected"]),
            n_detected=int(d["n_detected"]),
            n_matched=int(d["n_matched"]),
            symmetry_margin=int(d["symmetry_margin"]),
            rotation_det=float(d["rotation_det"]),
            predicted_tre_mm=tuple(float(v) for v in d.get("predicted_tre_mm", ())),
            targets_image_mm=points3(d.get("targets_image_mm", ())),
            targets_source=str(d.get("targets_source", "")),
            spheres=tuple(SphereMatch(**s) for s in d.get("spheres", ())),
            detection=DetectionSummary(
                method=str(det.get("method", "")),
                n_rejected=int(det.get("n_rejected", 0)),
                timings_s=dict(det.get("timings_s", {})),
            ),
            provenance=dict(d.get("provenance", {})),
            timings_s=dict(d.get("timings_s", {})),
            predicted_chain_error_mm=(
                None if d.get("predicted_chain_error_mm") is None else float(d["predicted_chain_error_mm"])
            ),
            chain_error_source=str(d.get("chain_error_source", "")),
            series_geometry=d.get("series_geometry"),
            face_offset_mm=None if d.get("face_offset_mm") is None else float(d["face_offset_mm"]),
            face_offset_se_mm=None if d.get("face_offset_se_mm") is None else float(d["face_offset_se_mm"]),
        )


@dataclass(frozen=True)
class RegistrationRecord:
    """Every ``POST /register``, accepted or refused (design.md §9).

    ``id`` is 0 and ``is_current`` False until the store has written it.  ``targets_image_mm``
    are the targets the request gave (None: the default targets, see ``figures``).
    """

    created_at: str
    status: RegistrationStatus
    config_hash: str
    software_version: str
    id: int = 0
    scan_id: int | None = None
    series_uid: str = ""
    reason: str = ""
    problem_title: str = ""
    http_status: int | None = None
    image_from_robot: Matrix4 | None = None
    fre_mm: float | None = None
    figures: RegistrationFigures | None = None
    targets_image_mm: Points3 | None = None
    joints_rad: tuple[float, ...] | None = None
    joints_received_at: str | None = None
    duration_s: float | None = None
    is_current: bool = False
    retired_at: str | None = None
    """When activating calibration ``retired_by_calibration`` retired it (status ``retired``)."""
    retired_by_calibration: int | None = None
    withdrawn_at: str | None = None
    """When it stopped being usable (status ``withdrawn``; ``reason`` says why)."""
    withdrawn_by_scan: int | None = None
    """The verification scan whose failed verification withdrew it (None: not withdrawn by one)."""
    withdrawn_by_verification: int | None = None
    """That stored verification (None: its error was beyond what matching can bridge, nothing stored)."""
    verified_by: int | None = None
    """A verification at another pose that passed against it (its evidence level ``verified``;
    service.registrations.evidence).  Derived from the verifications by the orchestrator, not stored."""


# ---- verifications -------------------------------------------------------------------------


@dataclass(frozen=True)
class SphereError:
    sphere: str
    robot_index: int
    error_mm: float


@dataclass(frozen=True)
class VerificationFigures:
    errors: tuple[SphereError, ...]
    n_expected: int
    n_detected: int
    n_matched: int
    max_verification_error_mm: float
    joints_rad: tuple[float, ...] | None = None
    joints_received_at: str | None = None

    def to_json(self) -> JSONDict:
        return {
            "errors": [vars(e) for e in self.errors],
            "n_expected": self.n_expected,
            "n_detected": self.n_detected,
            "n_matched": self.n_matched,
            "max_verification_error_mm": self.max_verification_error_mm,
            "joints_rad": None if self.joints_rad is None else list(self.joints_rad),
            "joints_received_at": self.joints_received_at,
        }

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> VerificationFigures:
        return cls(
            errors=tuple(SphereError(**e) for e in d.get("errors", ())),
            n_expected=int(d.get("n_expected", 0)),
            n_detected=int(d.get("n_detected", 0)),
            n_matched=int(d.get("n_matched", 0)),
            max_verification_error_mm=float(d.get("max_verification_error_mm", 0.0)),
            joints_rad=floats(d.get("joints_rad")),
            joints_received_at=d.get("joints_received_at"),
        )


@dataclass(frozen=True)
class VerificationRecord:
    """Every ``POST /verify`` (Bai 2018 §3, eq. 10); ``id`` is 0 until stored."""

    created_at: str
    registration_id: int
    scan_id: int
    series_uid: str
    passed: bool
    mean_mm: float
    rms_mm: float
    max_mm: float
    figures: VerificationFigures
    config_hash: str
    software_version: str
    id: int = 0
    histogram_path: str | None = None


@dataclass(frozen=True)
class RegistrationRefusal:
    """A registration the orchestrator refused: why, and the id of the ``refused`` record it stored
    (``None`` only when storing it failed too).  Returned, not raised, so the id travels typed."""

    registration_id: int | None
    error: OarmRegError | RobotLinkError
