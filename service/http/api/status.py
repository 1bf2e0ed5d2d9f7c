"""``GET /status`` and ``GET /robot/joints``."""

from __future__ import annotations

import shutil
import time
from datetime import UTC, datetime

from fastapi import APIRouter, Response

from drivers.errors import RobotLinkError
from registration import __version__
from service.http.api.deps import CtxDep, HttpDep
from service.http.api.models import (
    HealthProblemOut,
    JointsOut,
    LinkOut,
    ReadyOut,
    StatusOut,
    WithdrawalOut,
    registration_out,
    scan_out,
)
from service.http.api.problems import problem_responses
from service.http.health import collect_problems

router = APIRouter(tags=["status"])


@router.get(
    "/status",
    response_model=StatusOut,
    summary="Robot link, watcher, latest scan, current registration",
    responses=problem_responses(401),
)
def status(ctx: CtxDep, http: HttpDep) -> StatusOut:
    latest = ctx.db.scans.latest_complete()
    cur = ctx.orchestrator.current
    problems = collect_problems(ctx, http)
    w = ctx.orchestrator.withdrawal
    return StatusOut(
        healthy=not problems,
        problems=[p.detail for p in problems],
        problem_details=[HealthProblemOut(type=p.type, title=p.title, detail=p.detail) for p in problems],
        version=__version__,
        started_at=ctx.started_at.isoformat(),
        uptime_s=(datetime.now(UTC) - ctx.started_at).total_seconds(),
        auth_enabled=ctx.settings.auth_enabled,
        link=LinkOut(**ctx.capture.health()),
        watcher=ctx.watcher.state() if ctx.watcher is not None else {"mode": "disabled", "running": False},
        latest_scan=scan_out(latest) if latest else None,
        current_registration=registration_out(cur) if cur else None,
        registration_withdrawal=None if w is None else WithdrawalOut.model_validate(w, from_attributes=True),
        busy=ctx.orchestrator.busy,
        counts=ctx.db.counts(),
        config_hash=ctx.orchestrator.config_hash,
        listeners={
            **ctx.listeners(),
            "http_limits": http.limits.as_dict() if http.limits is not None else None,
        },
        active_calibration=_active_calibration(ctx),
        disk=_disk(ctx),
        gates={
            "max_verification_error_mm": ctx.settings.quality.max_verification_error_mm,
            "max_fre_mm": ctx.settings.quality.max_fre_mm,
        },
    )


MB = 1024**2
"""retention.max_disk_mb counts 1024² bytes (service.intake.retention)."""


def _disk(ctx: CtxDep) -> dict[str, float | None]:
    """Disk use against the retention quota: from the database, no folder walk."""
    try:
        free_mb: float | None = shutil.disk_usage(ctx.settings.data_dir).free / MB
    except OSError:
        free_mb = None
    return {
        "scans_mb": ctx.db.scans.stored_bytes() / MB,
        "quota_mb": ctx.settings.retention.max_disk_mb,
        "data_dir_free_mb": free_mb,
    }


@router.get(
    "/ready",
    response_model=ReadyOut,
    summary="Readiness: 200 when nothing is wrong, 503 listing each problem",
    responses={**problem_responses(401), 503: {"model": ReadyOut, "description": "not ready: see problems"}},
)
def ready(ctx: CtxDep, http: HttpDep, response: Response) -> ReadyOut:
    problems = collect_problems(ctx, http)
    if problems:
        response.status_code = 503
    return ReadyOut(
        ready=not problems,
        problems=[HealthProblemOut(type=p.type, title=p.title, detail=p.detail) for p in problems],
    )


def _active_calibration(ctx: CtxDep) -> dict[str, object] | None:
    act = ctx.db.calibrations.active()
    if act is None:
        return None
    return {
        "calibration_id": act.id,
        "calibration_hash": act.calibration_hash,
        "activated_at": act.activated_at,
        "predicted_held_out_rms_mm": (act.result or {}).get("predicted_held_out_rms_mm"),
        "in_use": not ctx.calibrations.inactive_reason,
        "not_in_use_reason": ctx.calibrations.inactive_reason,
    }


@router.get(
    "/robot/joints",
    response_model=JointsOut,
    summary="Latest joint angles from the robot link",
    responses=problem_responses(401, 409),
)
def robot_joints(ctx: CtxDep) -> JointsOut:
    h = ctx.capture.health()
    latest = ctx.capture.latest()
    if latest is None:
        raise RobotLinkError(
            f"no joint angles received from {h['url']} (link {h['state']}: {h['reason']}); check GET /status"
        )
    return JointsOut(
        joints_rad=list(latest.joints_rad),
        received_at=latest.received_at.isoformat(),
        age_s=max(0.0, time.monotonic() - latest.t_s),
        link=LinkOut(**h),
    )
