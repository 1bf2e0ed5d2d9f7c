"""``POST /qa/protocols``, ``GET /qa/protocols`` (paginated), ``GET /qa/protocols/{id}``;
``GET /qa/trend`` and ``GET /qa/trend.csv`` (QA checks and FRE over time, the drift rule).

A QA protocol is a named set of verification poses, so successive QA checks of a cell are
comparable; ``POST /verify`` names one with ``qa_protocol_id`` and ``qa_pose``.
"""

from __future__ import annotations

import math
from typing import Annotated

from fastapi import APIRouter, Query
from fastapi.responses import Response
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from service.errors import NotFoundError, QaProtocolError, QaProtocolNameTakenError
from service.http.api.deps import CtxDep, Limit, Offset, PrincipalDep, RecordId
from service.http.api.problems import problem_responses
from service.http.audit import audited
from service.registrations.qa_drift import drift
from service.runtime.context import ServiceContext
from service.store.qa import FrePoint, QaCheck, QaPose, QaProtocol, QaTrendPoint

router = APIRouter(tags=["qa"])

N_JOINTS = 6
"""The Stäubli TX60's joints: every pose names all six."""
MAX_JOINT_RAD = 2 * math.pi
"""No Stäubli joint turns further than ±360° (TX60 J6: ±270°)."""

PoseName = Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.\-]+$")]


class QaPoseIn(BaseModel):
    model_config = ConfigDict(extra="forbid")

    name: PoseName
    joints_rad: list[float] = Field(min_length=N_JOINTS, max_length=N_JOINTS, description="J1…J6 (rad)")

    @field_validator("joints_rad")
    @classmethod
    def _finite(cls, v: list[float]) -> list[float]:
        for i, q in enumerate(v):
            if not math.isfinite(q) or abs(q) > MAX_JOINT_RAD:
                raise ValueError(f"J{i + 1} = {q} rad is not a joint angle (finite, within ±2π rad)")
        return v


class QaProtocolIn(BaseModel):
    """``POST /qa/protocols``."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "examples": [
                {"name": "weekly", "poses": [{"name": "p1", "joints_rad": [0, 0, 1.571, 0, 0.785, 0.3]}]}
            ]
        },
    )

    name: Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.\- ]+$")]
    description: Annotated[str, Field(max_length=1000)] = ""
    poses: list[QaPoseIn] = Field(min_length=1, max_length=64)

    @model_validator(mode="after")
    def _unique_pose_names(self) -> QaProtocolIn:
        names = [p.name for p in self.poses]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"pose names must be unique within a protocol; repeated: {', '.join(dup)}")
        return self


class QaPoseOut(BaseModel):
    name: str
    joints_rad: list[float]


class QaProtocolOut(BaseModel):
    id: int
    name: str
    description: str
    created_at: str
    poses: list[QaPoseOut]


def protocol_out(p: QaProtocol) -> QaProtocolOut:
    return QaProtocolOut(
        id=p.id,
        name=p.name,
        description=p.description,
        created_at=p.created_at,
        poses=[QaPoseOut(name=q.name, joints_rad=list(q.joints_rad)) for q in p.poses],
    )


def resolve_pose(ctx: ServiceContext, protocol_id: int | None, pose: str | None) -> QaCheck | None:
    """The QA check a ``POST /verify`` names (``verification_id`` 0 until stored), checked before
    the verification runs; None when it names none.

    Raises
    ------
    QaProtocolError
        Only one of ``qa_protocol_id`` / ``qa_pose`` given, or the protocol has no such pose.
    NotFoundError
        No protocol with that id.
    """
    if protocol_id is None and pose is None:
        return None
    if protocol_id is None or pose is None:
        raise QaProtocolError(
            "a QA verification names both qa_protocol_id and qa_pose (the pose the robot is at); "
            "give both, or neither for a verification outside any protocol"
        )
    proto = ctx.db.qa.get_protocol(protocol_id)
    if proto is None:
        raise NotFoundError(f"QA protocol {protocol_id} does not exist; GET /qa/protocols lists them")
    if proto.pose(pose) is None:
        raise QaProtocolError(
            f"QA protocol {proto.id} ({proto.name!r}) has no pose {pose[:64]!r}; its poses: "
            + ", ".join(q.name for q in proto.poses)
        )
    return QaCheck(0, proto.id, pose)


@router.post(
    "/qa/protocols",
    response_model=QaProtocolOut,
    status_code=201,
    summary="Create a QA protocol: a named set of verification poses",
    responses=problem_responses(401, 409, 422),
)
def create_protocol(ctx: CtxDep, principal: PrincipalDep, body: QaProtocolIn) -> QaProtocolOut:
    with audited(ctx, principal, "qa_protocol_create", "qa_protocol") as note:
        if ctx.db.qa.find_by_name(body.name) is not None:
            raise QaProtocolNameTakenError(
                f"a QA protocol named {body.name!r} exists already; protocols are not edited "
                "(successive checks must stay comparable): choose a new name"
            )
        poses = tuple(QaPose(p.name, tuple(p.joints_rad)) for p in body.poses)
        new_id = ctx.db.qa.insert_protocol(body.name, body.description, poses)
        note(new_id, "created", f"{body.name!r}, {len(poses)} poses")
    proto = ctx.db.qa.get_protocol(new_id)
    assert proto is not None
    return protocol_out(proto)


@router.get(
    "/qa/protocols",
    response_model=list[QaProtocolOut],
    summary="Every QA protocol, newest first (paginated: limit, offset)",
    responses=problem_responses(401),
)
def list_protocols(ctx: CtxDep, limit: Limit = 100, offset: Offset = 0) -> list[QaProtocolOut]:
    return [protocol_out(p) for p in ctx.db.qa.list_protocols(limit, offset)]


@router.get(
    "/qa/protocols/{protocol_id}",
    response_model=QaProtocolOut,
    summary="One QA protocol",
    responses=problem_responses(401, 404),
)
def get_protocol(ctx: CtxDep, protocol_id: RecordId) -> QaProtocolOut:
    proto = ctx.db.qa.get_protocol(protocol_id)
    if proto is None:
        raise NotFoundError(f"QA protocol {protocol_id} does not exist; GET /qa/protocols lists them")
    return protocol_out(proto)


# ---- QA trend --------------------------------------------------------------------------------

CalibrationQuery = Annotated[
    int | None,
    Query(ge=1, le=2**63 - 1, description="Only records made under this calibration (GET /calibrations)"),
]


class QaTrendCheckOut(BaseModel):
    verification_id: int
    created_at: str
    protocol_id: int
    protocol_name: str
    pose: str
    mean_mm: float
    max_mm: float
    passed: bool
    registration_id: int
    calibration_id: int | None = Field(
        description="Active when the registration was made; null: nominal model"
    )
    withdrawn: bool


class FreOut(BaseModel):
    registration_id: int
    created_at: str
    fre_mm: float
    calibration_id: int | None
    face_offset_mm: float | None = Field(
        default=None,
        description="The scan's face offset β (mm): a drift is a phantom or scanner change; null: not fitted",
    )


class DriftOut(BaseModel):
    """The drift rule on the last ``window`` QA checks under the active calibration."""

    calibration_id: int | None
    window: int
    limit_mm: float
    rise_limit_mm: float
    means_mm: list[float]
    drifting: bool
    detail: str


class QaTrendOut(BaseModel):
    checks: list[QaTrendCheckOut]
    fre: list[FreOut]
    drift: DriftOut


def _trend(
    ctx: ServiceContext, calibration_id: int | None, limit: int, offset: int
) -> tuple[list[QaTrendPoint], list[FrePoint]]:
    if calibration_id is not None and ctx.db.calibrations.get(calibration_id) is None:
        raise NotFoundError(f"calibration {calibration_id} does not exist; GET /calibrations lists them")
    t = ctx.db.qa_trend
    return (
        t.checks(calibration_id, limit=limit, offset=offset),
        t.fre(calibration_id, limit=limit, offset=offset),
    )


def drift_state(ctx: ServiceContext) -> DriftOut:
    q = ctx.settings.qa
    cal_id = ctx.db.calibrations.active_id()
    means = ctx.db.qa_trend.last_means(cal_id, q.drift_window)
    v = drift(means, window=q.drift_window, limit_mm=q.drift_mean_mm, rise_mm=q.drift_rise_mm)
    return DriftOut(
        calibration_id=cal_id,
        window=q.drift_window,
        limit_mm=q.drift_mean_mm,
        rise_limit_mm=q.drift_rise_mm,
        means_mm=means,
        drifting=v is not None,
        detail="" if v is None else v.describe(),
    )


@router.get(
    "/qa/trend",
    response_model=QaTrendOut,
    summary="QA checks (mean / max, PASS/FAIL) and registrations' FRE over time, oldest first (paginated)",
    responses=problem_responses(401, 404, 422),
)
def qa_trend(
    ctx: CtxDep, calibration_id: CalibrationQuery = None, limit: Limit = 100, offset: Offset = 0
) -> QaTrendOut:
    checks, fre = _trend(ctx, calibration_id, limit, offset)
    return QaTrendOut(
        checks=[QaTrendCheckOut(**vars(c)) for c in checks],
        fre=[FreOut(**vars(f)) for f in fre],
        drift=drift_state(ctx),
    )


CSV_COLUMNS = (
    "kind", "id", "created_at", "calibration_id", "protocol_id", "protocol_name", "pose",
    "mean_mm", "max_mm", "passed", "registration_id", "withdrawn", "fre_mm", "face_offset_mm",
)  # fmt: skip
"""``GET /qa/trend.csv``: one row per QA check (``kind`` qa_check) then per registration (``kind`` fre)."""


@router.get(
    "/qa/trend.csv",
    response_class=Response,
    summary="GET /qa/trend's checks and FRE as CSV (same filter and pages)",
    responses={**problem_responses(401, 404, 422), 200: {"content": {"text/csv": {}}}},
)
def qa_trend_csv(
    ctx: CtxDep, calibration_id: CalibrationQuery = None, limit: Limit = 100, offset: Offset = 0
) -> Response:
    import csv
    import io

    checks, fre = _trend(ctx, calibration_id, limit, offset)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\r\n")
    w.writerow(CSV_COLUMNS)

    def cal(c: int | None) -> str:
        return "" if c is None else str(c)

    for c in checks:
        w.writerow(
            ("qa_check", c.verification_id, c.created_at, cal(c.calibration_id), c.protocol_id,
             c.protocol_name, c.pose, repr(c.mean_mm), repr(c.max_mm), "PASS" if c.passed else "FAIL",
             c.registration_id, int(c.withdrawn), "", "")
        )  # fmt: skip
    for f in fre:
        w.writerow(
            ("fre", f.registration_id, f.created_at, cal(f.calibration_id), "", "", "", "", "", "",
             f.registration_id, "", repr(f.fre_mm),
             "" if f.face_offset_mm is None else repr(f.face_offset_mm))
        )  # fmt: skip
    return Response(
        buf.getvalue(),
        media_type="text/csv; charset=utf-8",
        headers={"Content-Disposition": 'attachment; filename="qa-trend.csv"'},
    )
