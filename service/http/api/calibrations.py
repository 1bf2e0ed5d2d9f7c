"""``POST /calibrations``, ``GET /calibrations[/{id}]``, ``GET /calibrations/{id}/robot.urdf``,
``POST /calibrations/{id}/activate`` (design.md §9)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

import anyio.to_thread
from fastapi import APIRouter, Body, Query, Request, Response
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ConfigDict, Field, model_validator

from service.errors import ActivationRetiresCurrentError, NotFoundError
from service.http.api.deps import CtxDep, Offset, RecordId
from service.http.api.models import DbId
from service.http.api.problems import problem_for, problem_responses
from service.registrations.calibration_jobs import CalibrationJobs, CalibrationRefusal, CalibrationRequest
from service.runtime.context import ServiceContext
from service.store.calibrations import CalibrationRecord

router = APIRouter(tags=["calibration"])


class CalibrateRequest(BaseModel):
    """``POST /calibrations``: the scans of one session (one O-arm placement, K ≥ 6 poses)."""

    model_config = ConfigDict(
        extra="forbid", json_schema_extra={"examples": [{"last": 10}, {"scan_ids": [3, 4, 5, 6, 7, 8]}]}
    )

    scan_ids: list[DbId] | None = Field(default=None, max_length=200, description="Scans (GET /scans).")
    last: int | None = Field(default=None, ge=1, le=200, description="Or: the last K complete scans.")
    parameter_set: Literal["full", "offsets", "hand-eye"] = Field(
        "full", description="Robot parameters to estimate besides rod and O-arm placement."
    )
    drop_weak: bool = Field(
        False,
        description="Fix the robot parameters the poses excite least at nominal (reported as dropped) until "
        "the identification condition number is ≤ max_condition (100 if not given).",
    )
    max_condition: float | None = Field(
        None,
        gt=1.0,
        description="Optional extra refusal above this identification condition number (off by default: "
        "the calibration is refused on its predicted error over the working volume, not on the condition "
        "number).",
    )

    @model_validator(mode="after")
    def _one_source(self) -> CalibrateRequest:
        if (self.scan_ids is None) == (self.last is None):
            raise ValueError('give exactly one of "scan_ids" or "last"')
        return self


class CalibrationOut(BaseModel):
    id: int
    status: str = Field(description="running | done | refused")
    reason: str = ""
    problem_title: str = ""
    is_active: bool
    activated_at: str | None = None
    withdrawn_at: str | None = Field(
        None, description="Set when a scan it was fitted to changed content: it can never be activated."
    )
    withdrawn_reason: str = ""
    created_at: str
    finished_at: str | None = None
    duration_s: float | None = None
    scan_ids: list[int]
    frame_of_reference_uid: str
    calibration_hash: str = Field("", description="SHA-256 of the calibrated URDF and tool0_from_phantom.")
    params: dict[str, Any]
    urdf_url: str | None = None
    fit_rms_mm: float | None = None
    leave_one_pose_out_mean_mm: float | None = None
    leave_one_pose_out_max_mm: float | None = None
    predicted_held_out_rms_mm: float | None = Field(
        None, description="Expected RMS sphere error at unseen poses after a one-scan registration."
    )
    target_rms_mm: float | None = Field(
        None,
        description="The pose planner's target (calibration.target_rms_mm) the prediction is compared with.",
    )
    target_met: bool | None = Field(None, description="predicted_held_out_rms_mm ≤ target_rms_mm.")
    tool0_from_phantom: list[list[float]] | None = None
    image_from_robot: list[list[float]] | None = Field(
        None, description="Of the calibration session's placement."
    )
    parameters: list[dict[str, Any]] = Field([], description="name, value, std_error, unit.")
    poses: list[dict[str, Any]] = Field([], description="Per pose: residuals per sphere, LOPO error.")
    identification: dict[str, Any] | None = None
    dropped_parameters: list[str] = []
    outlier_poses: list[str] = []
    provenance: dict[str, Any] = {}
    timings_s: dict[str, float] = {}


def calibration_out(rec: CalibrationRecord) -> CalibrationOut:
    r = rec.result or {}
    keys = (
        "fit_rms_mm", "leave_one_pose_out_mean_mm", "leave_one_pose_out_max_mm", "predicted_held_out_rms_mm",
        "target_rms_mm", "target_met", "tool0_from_phantom", "image_from_robot", "parameters", "poses",
        "identification",
        "dropped_parameters", "outlier_poses", "provenance", "timings_s",
    )  # fmt: skip
    return CalibrationOut(
        id=rec.id,
        status=rec.status,
        reason=rec.reason,
        problem_title=rec.problem_title,
        is_active=rec.is_active,
        activated_at=rec.activated_at,
        withdrawn_at=rec.withdrawn_at,
        withdrawn_reason=rec.withdrawn_reason,
        created_at=rec.created_at,
        finished_at=rec.finished_at,
        duration_s=rec.duration_s,
        scan_ids=list(rec.scan_ids),
        frame_of_reference_uid=rec.frame_of_reference_uid,
        calibration_hash=rec.calibration_hash,
        params=rec.params,
        urdf_url=f"/calibrations/{rec.id}/robot.urdf" if rec.urdf_text else None,
        **{k: r[k] for k in keys if k in r},
    )


def _jobs(ctx: ServiceContext) -> CalibrationJobs:
    jobs: CalibrationJobs = ctx.calibrations
    return jobs


@router.post(
    "/calibrations",
    status_code=202,
    response_model=CalibrationOut,
    summary="Calibrate robot, rod and O-arm placement from K ≥ 6 recorded scans (runs in the background)",
    description=(
        "Answers 202 with the `running` calibration; progress is published on `/events` "
        "(`calibration_progress` pose i of K, then `calibration_done` or `calibration_refused`), and "
        "`GET /calibrations/{id}` shows the outcome.  Fewer than 6 scans or scans of several O-arm "
        "placements (FrameOfReferenceUID) are refused at once (409, stored, `calibration_id`)."
    ),
    responses=problem_responses(401, 404, 409, 422),
)
async def post_calibration(
    request: Request, ctx: CtxDep, body: CalibrateRequest
) -> CalibrationOut | JSONResponse:
    req = CalibrationRequest(
        scan_ids=None if body.scan_ids is None else tuple(body.scan_ids),
        last=body.last,
        parameter_set=body.parameter_set,
        drop_weak=body.drop_weak,
        max_condition=body.max_condition,
    )
    rec = await anyio.to_thread.run_sync(_jobs(ctx).start, req)
    if isinstance(rec, CalibrationRefusal):
        return problem_for(request, rec.error, calibration_id=rec.calibration_id)
    return calibration_out(rec)


@router.get("/calibrations", response_model=list[CalibrationOut], summary="Every calibration, newest first")
def list_calibrations(
    ctx: CtxDep,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
    offset: Offset = 0,
) -> list[CalibrationOut]:
    return [calibration_out(r) for r in ctx.db.calibrations.list(limit, offset)]


def _get(ctx: ServiceContext, calibration_id: int) -> CalibrationRecord:
    rec = ctx.db.calibrations.get(calibration_id)
    if rec is None:
        raise NotFoundError(f"calibration {calibration_id} does not exist; GET /calibrations lists them")
    return rec


@router.get(
    "/calibrations/{calibration_id}",
    response_model=CalibrationOut,
    summary="One calibration: figures, per-pose residuals, LOPO, parameters with standard errors",
    responses=problem_responses(401, 404),
)
def get_calibration(ctx: CtxDep, calibration_id: RecordId) -> CalibrationOut:
    return calibration_out(_get(ctx, calibration_id))


@router.get(
    "/calibrations/{calibration_id}/robot.urdf",
    summary="The calibrated URDF (corrected joint origins)",
    responses=problem_responses(401, 404),
)
def get_urdf(ctx: CtxDep, calibration_id: RecordId) -> Response:
    rec = _get(ctx, calibration_id)
    if not rec.urdf_text:
        raise NotFoundError(f"calibration {calibration_id} is {rec.status}: it has no URDF")
    return Response(
        rec.urdf_text,
        media_type="application/xml",
        headers={"Content-Disposition": f'attachment; filename="oarmreg-calibration-{rec.id}.urdf"'},
    )


class ActivateRequest(BaseModel):
    """``POST /calibrations/{id}/activate`` (optional body)."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [{"force": True}]})

    force: bool = Field(
        False,
        description="Activate although a registration is current (it is retired: navigation loses it "
        "until the next /register).  Without it, activation while one is current answers 409.",
    )


@router.post(
    "/calibrations/{calibration_id}/activate",
    response_model=CalibrationOut,
    summary="Use this calibration for /register; retires the current registration",
    description=(
        "Every accepted registration becomes `retired` and none is current until the next `/register` "
        "(push channels report INVALID; `registration_retired` is published).  While a registration is "
        'current the request must say `{"force": true}`, else 409 and nothing changes.'
    ),
    responses=problem_responses(401, 404, 409),
)
async def activate(
    ctx: CtxDep, calibration_id: RecordId, body: Annotated[ActivateRequest | None, Body()] = None
) -> CalibrationOut:
    current = ctx.orchestrator.current
    if current is not None and not (body is not None and body.force):
        _get(ctx, calibration_id)  # an unknown id is still 404
        raise ActivationRetiresCurrentError(
            f"registration {current.id} is current; activating calibration {calibration_id} retires it and "
            "navigation has no registration until the next POST /register; repeat with "
            '{"force": true} to go ahead'
        )
    rec, _ = await anyio.to_thread.run_sync(_jobs(ctx).activate, calibration_id)
    return calibration_out(rec)
