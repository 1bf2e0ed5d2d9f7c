"""Request and response bodies (separate models; internals never leak).

Units are in the field names; matrices are nested lists ``[[r00, r01, r02, tx], ...]``
(row-major, 4 × 4, mm).  ``image_from_robot`` maps robot-frame points (Stäubli world
frame = URDF ``base``) to image points (DICOM patient coordinates, LPS, of the scan's
FrameOfReferenceUID): ``p_image = image_from_robot @ p_robot``.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import (
    AliasChoices,
    AliasPath,
    BaseModel,
    ConfigDict,
    Field,
    StrictFloat,
    StrictInt,
    computed_field,
    field_validator,
    model_validator,
)

from service.records import RegistrationRecord, ScanRecord, VerificationRecord
from service.registrations.evidence import calibration_of, evidence_of

EXAMPLE_MATRIX: list[Any] = [
    [0.0, -1.0, 0.0, 412.5],
    [1.0, 0.0, 0.0, -35.2],
    [0.0, 0.0, 1.0, -610.0],
    [0.0, 0.0, 0.0, 1.0],
]

MAX_DB_ID = 2**63 - 1
"""SQLite's INTEGER range: row ids are 1 … 2^63 − 1 (sqlite.org/lang_createtable.html#rowid)."""
MAX_OFFSET = 2**63 - 1

DbId = Annotated[StrictInt, Field(ge=1, le=MAX_DB_ID)]
"""A record id in a request body: a JSON integer (not ``true``, not ``"3"``) in SQLite's row-id range."""

Matrix4 = list[list[float]]
Point3 = list[float]
StrictPoint3 = list[StrictFloat]
"""A request point: JSON numbers only (no ``true``, no numeric strings)."""


class _Out(BaseModel):
    model_config = ConfigDict(extra="ignore", from_attributes=True)


def _from(parent: str, name: str) -> AliasChoices:
    """Read field ``name`` from the record's ``parent`` attribute (e.g. ``figures.fle_mm``)."""
    return AliasChoices(name, AliasPath(parent, name))


# ---- requests ------------------------------------------------------------------------------


class RegisterRequest(BaseModel):
    """``POST /register``."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={"examples": [{}, {"scan_id": 3, "targets_image_mm": [[10.0, -25.5, 140.0]]}]},
    )

    scan_id: DbId | None = Field(
        default=None, description="Scan to register (GET /scans); default: the latest complete scan."
    )
    targets_image_mm: list[StrictPoint3] | None = Field(
        default=None,
        description=(
            "Target points in the IMAGE frame (DICOM LPS mm, the navigation UI's space) at which to report "
            "Fitzpatrick's predicted TRE, e.g. the planned screw entry points.  Default: 6 points "
            "`quality.default_target_distance_mm` (150 mm) from the phantom centre along the robot axes."
        ),
        max_length=1000,
    )

    phantom_confirmed: bool = Field(
        default=False,
        description="The phantom file is the phantom scanned: register even when far more spheres are "
        "detected than it has, or the best pose explains a small share of them (refused otherwise, "
        '409 "Check the phantom file").',
    )
    allow_superseded: bool = Field(
        default=False,
        description="Register and make current even though the service has newer evidence against this "
        "scan (a newer scan at the same FrameOfReferenceUID has an accepted registration or a failed "
        "verification, or a verification withdrew this scan's registration: docs/safety.md, \"Which "
        'registration may be current").  Needs `reason`; audited.',
    )
    reason: str | None = Field(
        default=None,
        min_length=3,
        max_length=500,
        description="Why `allow_superseded` is used (stored in the audit log and the registration's "
        "provenance).",
    )

    @model_validator(mode="after")
    def _override_needs_a_reason(self) -> RegisterRequest:
        if self.allow_superseded and not (self.reason or "").strip():
            raise ValueError("allow_superseded: true needs a reason (why the newer evidence does not apply)")
        if self.reason is not None and not self.allow_superseded:
            raise ValueError("reason is only taken with allow_superseded: true")
        return self

    @model_validator(mode="before")
    @classmethod
    def _renamed(cls, data: Any) -> Any:
        if isinstance(data, dict) and "targets_mm" in data:  # one frame per name
            raise ValueError(
                "targets_mm was renamed targets_image_mm (image frame, DICOM LPS mm); the CLI's robot-frame "
                "targets are targets_robot_mm"
            )
        return data

    @field_validator("targets_image_mm")
    @classmethod
    def _three(cls, v: list[StrictPoint3] | None) -> list[StrictPoint3] | None:
        if v is None:
            return v
        for i, p in enumerate(v):
            if len(p) != 3:
                raise ValueError(f"targets_image_mm[{i}] must be [x, y, z] in mm, got {len(p)} values")
            if any(abs(c) > 1e5 or c != c for c in p):
                raise ValueError(f"targets_image_mm[{i}] = {p} is not a finite position in mm")
        return v


class VerifyRequest(BaseModel):
    """``POST /verify``."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [{}, {"scan_id": 4}]})

    scan_id: DbId | None = Field(
        default=None,
        description="A scan newer than the current registration's scan; default: the latest complete scan.",
    )
    qa_protocol_id: DbId | None = Field(
        default=None, description="The QA protocol this check belongs to (with `qa_pose`)."
    )
    qa_pose: str | None = Field(
        default=None, min_length=1, max_length=64, description="The protocol's pose the robot is at."
    )


# ---- responses -----------------------------------------------------------------------------


class Health(_Out):
    status: Literal["ok", "unhealthy"] = "ok"
    version: str
    problems: list[str] = Field(
        [], description="Why the service is unhealthy (e.g. its database file vanished) and what to do."
    )


class EventTicketOut(_Out):
    ticket: str = Field(
        description="Single use; pass as GET /events?ticket=… (EventSource cannot send headers)."
    )
    expires_in_s: float
    url: str


class AuditOut(_Out):
    id: int
    at: str
    principal: str = Field(description="token:<12 hex of the token's SHA-256> or none-loopback-only.")
    action: str = Field(description="register | verify | activate | delete")
    target: str
    target_id: int | None
    outcome: str
    detail: str


class LinkOut(_Out):
    url: str
    state: str = Field(description="connected | stale | down")
    reason: str
    last_frame_age_s: float | None
    history_s: float = Field(description="Span of joint history currently buffered, s.")
    max_receive_gap_s: float | None = Field(
        None, description="Largest time between two received joint frames over the last 60 s, s."
    )
    in_motion: bool | None = Field(
        None,
        description="The controller's last STATUS in_motion: true, false, or null (unknown or no STATUS). "
        "TRUE inside a scan's stillness window refuses the scan as moved.",
    )
    down_events: int = Field(0, description="Times the link went down since the service started.")
    connect_failures: int = Field(
        0, description="Reconnect attempts that failed during those outages (each logged at DEBUG only)."
    )


class JointsOut(_Out):
    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "joints_rad": [0.1, -0.3, 1.9, 0.0, 0.8, 0.0],
                    "received_at": "2025-01-01T10:00:00+00:00",
                    "age_s": 0.012,
                    "link": {
                        "url": "simple-message://10.0.0.5:11002",
                        "state": "connected",
                        "reason": "receiving joint frames",
                        "last_frame_age_s": 0.012,
                        "history_s": 120.0,
                    },
                }
            ]
        }
    )
    joints_rad: list[float]
    received_at: str
    age_s: float
    link: LinkOut


class JointSnapshotOut(_Out):
    captured_at: str
    link_url: str
    link_state: str
    link_reason: str
    joints_rad: list[float] | None
    joints_received_at: str | None
    still: bool
    max_deviation_rad: float | None
    covered_s: float | None
    n_samples: int
    window_s: float
    stillness_reason: str
    verdict: str = Field(
        "",
        description="still | moved | incomplete (docs/safety.md, Stillness and health).",
    )


class ScanOut(_Out):
    id: int
    series_uid: str
    frame_of_reference_uid: str
    folder: str
    arrived_at: str
    n_files: int
    n_slices: int
    rows: int
    columns: int
    image_from_voxel: Matrix4 | None = Field(
        default=None,
        description="(i, j, k, 1) → LPS mm, 4 × 4 row-major.",
        validation_alias=_from("geometry", "image_from_voxel"),
    )
    spacing_mm: list[float] | None = Field(
        default=None,
        description="Voxel size along (column, row, slice), mm.",
        validation_alias=_from("geometry", "spacing_mm"),
    )
    status: str = Field(description="receiving | complete | reopened | replaced | invalid (docs/safety.md)")
    reason: str
    seen_count: int = Field(
        description="How often the series was exported (re-exports are deduplicated by UID)."
    )
    joints: JointSnapshotOut | None = Field(validation_alias=AliasChoices("joints", "snapshot"))


class SphereResidual(_Out):
    sphere: str = Field(description="Phantom hole id, e.g. '+x-r1c2'.")
    robot_index: int
    image_index: int
    residual_mm: float


ONE_SCAN_TRE_LABEL = "one-scan TRE, this pose only"
"""What Fitzpatrick's predicted TRE of one scan is: the error at the scan's own pose, not elsewhere."""


class ExpectedErrorOut(_Out):
    """The honest figure first: what the registration is expected to deliver where the robot works."""

    predicted_chain_error_mm: float | None = Field(
        description="Expected error at the robot's working poses (mm RMS): the active calibration's "
        "posterior figure, or the nominal model's prior when the cell is not calibrated."
    )
    calibrated: bool = Field(description="Whether an active calibration backs that figure.")
    calibration_id: int | None = None
    basis: str = Field(description="Where the figure comes from, in words.")
    one_scan_tre_max_mm: float | None = Field(
        default=None,
        description="Fitzpatrick's predicted TRE of this one scan, max over the targets: valid at this "
        "pose only (the chain's error at other poses is not in it).",
    )
    one_scan_tre_label: str = ONE_SCAN_TRE_LABEL


def expected_error_of(rec: RegistrationRecord) -> ExpectedErrorOut | None:
    """The honest figures of an accepted (or once accepted) registration; None without figures."""
    fig = rec.figures
    if fig is None:
        return None
    cal_id, _ = calibration_of(fig.provenance)
    calibrated = cal_id is not None
    chain = fig.predicted_chain_error_mm
    source = fig.chain_error_source or ("calibration posterior" if calibrated else "nominal model prior")
    basis = (
        f"calibration {cal_id} backs it ({source})"
        if calibrated
        else f"the cell is not calibrated: {source}; expect about this error at poses other than the "
        "registration scan's"
    )
    return ExpectedErrorOut(
        predicted_chain_error_mm=chain,
        calibrated=calibrated,
        calibration_id=None if cal_id is None else int(cal_id),
        basis=basis,
        one_scan_tre_max_mm=max(fig.predicted_tre_mm) if fig.predicted_tre_mm else None,
    )


class EvidenceOut(_Out):
    """What backs the registration's robot side (docs/safety.md, "Evidence levels")."""

    level: Literal["calibrated", "verified", "unverified"] = Field(
        description="calibrated: an active calibration under the same robot settings backs it; verified: "
        "a verification at another pose passed against it; unverified: neither (nominal model and the "
        "configured rod) — served, but one scan cannot see a robot-side error."
    )
    summary: str = Field(description="One sentence: what the level rests on.")
    action: str = Field(default="", description="What to do to raise it (empty when nothing is needed).")


class RegistrationOut(_Out):
    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "id": 3,
                    "status": "accepted",
                    "reason": "",
                    "is_current": True,
                    "scan_id": 2,
                    "series_uid": "1.2.826.0.1.3680043.8.498.1",
                    "created_at": "2025-01-01T10:00:05+00:00",
                    "image_from_robot": EXAMPLE_MATRIX,
                    "fre_mm": 0.06,
                    "fle_mm": 0.062,
                    "n_expected": 28,
                    "n_detected": 28,
                    "n_matched": 28,
                    "predicted_tre_mm": [0.05, 0.05, 0.06, 0.05, 0.05, 0.06],
                    "targets_image_mm": [[562.5, -35.2, -610.0]],
                    "symmetry_margin": 16,
                    "rotation_det": 1.0,
                }
            ]
        }
    )

    evidence: EvidenceOut | None = Field(
        default=None,
        description="What backs the robot side, first: calibrated, verified or unverified (null for a "
        "refused registration).",
    )
    expected_error: ExpectedErrorOut | None = Field(
        default=None,
        description="First, the honest figure: the expected error at the robot's working poses and "
        "whether a calibration backs it; then the one-scan TRE, labelled as valid at this pose only "
        "(null for a refused registration).",
    )
    id: int
    status: str = Field(description="accepted | refused | retired | withdrawn")
    reason: str = Field(description="Why it was refused or withdrawn (empty when accepted).")
    withdrawn_by_scan: int | None = Field(
        default=None, description="The verification scan whose failed verification withdrew it."
    )
    withdrawn_by_verification: int | None = Field(
        default=None,
        description="That verification (null with withdrawn_by_scan set: it could not be computed).",
    )
    problem_title: str = ""
    is_current: bool
    scan_id: int | None
    series_uid: str
    created_at: str
    image_from_robot: Matrix4 | None = Field(
        default=None, description="4 × 4 row-major, mm: p_image(LPS) = image_from_robot @ p_robot."
    )
    fre_mm: float | None = Field(
        default=None, description="RMS residual over the matched spheres (not an accuracy figure)."
    )
    fle_mm: float | None = Field(
        default=None,
        description="FLE implied by FRE: FRE·√(N/(N−2)).",
        validation_alias=_from("figures", "fle_mm"),
    )
    n_expected: int | None = Field(default=None, validation_alias=_from("figures", "n_expected"))
    n_detected: int | None = Field(default=None, validation_alias=_from("figures", "n_detected"))
    n_matched: int | None = Field(default=None, validation_alias=_from("figures", "n_matched"))
    spheres: list[SphereResidual] = Field([], validation_alias=_from("figures", "spheres"))
    predicted_tre_mm: list[float] = Field(
        [],
        description="Fitzpatrick's predicted TRE at targets_image_mm: one-scan TRE, this pose only "
        "(expected_error.predicted_chain_error_mm is the figure at other poses).",
        validation_alias=_from("figures", "predicted_tre_mm"),
    )
    predicted_chain_error_mm: float | None = Field(
        default=None,
        description="Predicted error of the robot chain over the working volume (mm RMS): the active "
        "calibration's posterior figure, or the nominal model's prior (1 mm) when none.",
        validation_alias=_from("figures", "predicted_chain_error_mm"),
    )
    series_geometry: dict[str, Any] | None = Field(
        default=None,
        description="The scan's volume (ImagePositionPatient range, orientation, rows/columns, spacing, "
        "FOV circle), for `oarmreg calibrate plan`.",
        validation_alias=_from("figures", "series_geometry"),
    )
    targets_image_mm: list[Point3] = Field([], validation_alias=AliasPath("figures", "targets_image_mm"))
    targets_source: str = Field("", validation_alias=_from("figures", "targets_source"))
    symmetry_margin: int | None = Field(
        default=None,
        description="Matched spheres, best minus runner-up hypothesis.",
        validation_alias=_from("figures", "symmetry_margin"),
    )
    rotation_det: float | None = Field(default=None, validation_alias=_from("figures", "rotation_det"))
    joints_rad: list[float] | None = None
    joints_received_at: str | None = None
    config_hash: str
    software_version: str
    duration_s: float | None = None
    retired_at: str | None = None
    retired_by_calibration: int | None = None
    provenance: dict[str, Any] = Field({}, validation_alias=_from("figures", "provenance"))
    timings_s: dict[str, float] = Field({}, validation_alias=_from("figures", "timings_s"))
    face_offset_mm: float | None = Field(
        default=None,
        description="The phantom's face offset β of this scan: how far every detected sphere centre sat "
        "along its hole's outward axis from the phantom file's position, fitted with the pose and "
        "removed (mm; negative: deeper in the hole).  A drift over time is a phantom or scanner "
        "change (docs/detection-settings.md).  Null: not fitted.",
        validation_alias=_from("figures", "face_offset_mm"),
    )
    face_offset_se_mm: float | None = Field(
        default=None,
        description="β's least-squares standard error (mm).",
        validation_alias=_from("figures", "face_offset_se_mm"),
    )
    pacs_export: PacsExportOut | None = Field(
        default=None, description="Its archive to the PACS (GET /registrations/{id} only; null: none queued)."
    )


class PacsExportOut(_Out):
    """The archive of a registration's Spatial Registration object to the PACS."""

    state: str = Field(description="pending | sent | failed")
    destination: str = Field(description="AE@host:port of the PACS (+tls when TLS is on)")
    attempts: int
    dimse_status: int | None = Field(default=None, description="The PACS's C-STORE status, when it answered.")
    reason: str = Field(description="What happened at the last attempt (empty before the first).")
    sop_instance_uid: str
    queued_at: str
    updated_at: str


class VerificationError(_Out):
    sphere: str
    robot_index: int
    error_mm: float


class VerificationOut(_Out):
    id: int
    created_at: str
    registration_id: int
    scan_id: int
    series_uid: str
    passed: bool = Field(description="max_mm ≤ quality.max_verification_error_mm")
    mean_mm: float
    rms_mm: float
    max_mm: float
    n_expected: int = Field(validation_alias=_from("figures", "n_expected"))
    n_detected: int = Field(validation_alias=_from("figures", "n_detected"))
    n_matched: int = Field(validation_alias=_from("figures", "n_matched"))
    errors: list[VerificationError] = Field(validation_alias=_from("figures", "errors"))
    gate_mm: float = Field(
        0.0,
        validation_alias=AliasChoices("gate_mm", AliasPath("figures", "max_verification_error_mm")),
        description="The gate it was judged against: quality.max_verification_error_mm at the time, mm.",
    )
    histogram_path: str | None = Field(default=None, exclude=True)
    config_hash: str
    software_version: str

    @computed_field  # type: ignore[prop-decorator]
    @property
    def histogram_url(self) -> str | None:
        return f"/verifications/{self.id}/histogram.png" if self.histogram_path else None


class WithdrawalOut(_Out):
    """Why nothing is current: a verification withdrew the registration (docs/safety.md)."""

    registration_id: int
    verification_scan_id: int
    verification_id: int | None = Field(
        description="The failed verification (null: it could not be computed, the error being beyond "
        "what matching can bridge)."
    )
    reason: str
    withdrawn_at: str
    predicted_chain_error_mm: float | None
    calibrated: bool
    gate_mm: float = Field(description="quality.max_verification_error_mm")
    likely_cause: Literal["cell-not-calibrated", "phantom-or-oarm-moved"]
    cause: str = Field(description="The likely cause in words.")
    action: str = Field(description="What to do.")


class HealthProblemOut(_Out):
    type: str = Field(
        description="Stable problem type, e.g. robot-link-down (docs/safety.md, Stillness and health)."
    )
    title: str
    detail: str = Field(description="What happened and what to do.")


class ReadyOut(_Out):
    ready: bool
    problems: list[HealthProblemOut] = []


class StatusOut(_Out):
    version: str
    started_at: str
    uptime_s: float
    auth_enabled: bool
    link: LinkOut
    watcher: dict[str, Any]
    latest_scan: ScanOut | None
    current_registration: RegistrationOut | None
    registration_withdrawal: WithdrawalOut | None = Field(
        None, description="Why nothing is current, when a verification withdrew the registration."
    )
    busy: bool = Field(description="A registration or verification is running.")
    counts: dict[str, int]
    config_hash: str
    listeners: dict[str, Any] = Field(
        default_factory=dict,
        description="DICOM SCP and OpenIGTLink server: enabled, host, port, associations / clients.",
    )
    healthy: bool = True
    problems: list[str] = Field([], description="Why the service is unhealthy and what to do.")
    problem_details: list[HealthProblemOut] = Field(
        [], description="The same problems, typed (docs/safety.md, Stillness and health)."
    )
    active_calibration: dict[str, Any] | None = Field(
        None, description="calibration_id, calibration_hash, activated_at; null: the nominal model and rod."
    )
    disk: dict[str, float | None] | None = Field(
        None,
        description="scans_mb (the recorded scan files not yet deleted), quota_mb (retention.max_disk_mb; "
        "null: no quota), data_dir_free_mb (free space of the data folder's file system).",
    )
    gates: dict[str, float] = Field(
        default_factory=dict,
        description="The quality gates the page judges figures against, mm: max_verification_error_mm "
        "(a verification's pass limit, and what the expected error at working poses is compared with), "
        "max_fre_mm.",
    )


# ---- converters ----------------------------------------------------------------------------


def scan_out(scan: ScanRecord) -> ScanOut:
    return ScanOut.model_validate(scan, from_attributes=True)


def registration_out(rec: RegistrationRecord) -> RegistrationOut:
    out = RegistrationOut.model_validate(rec, from_attributes=True)
    ev = evidence_of(rec)
    out.evidence = None if ev is None else EvidenceOut(level=ev.level, summary=ev.summary, action=ev.action)
    out.expected_error = expected_error_of(rec)
    return out


def verification_out(rec: VerificationRecord) -> VerificationOut:
    return VerificationOut.model_validate(rec, from_attributes=True)
