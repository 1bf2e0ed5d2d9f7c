"""``POST /verify``, ``GET /verifications`` (paginated), ``GET /verifications/{id}`` and its histogram PNG."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Annotated

import anyio.to_thread
from fastapi import APIRouter, Body
from fastapi.responses import FileResponse

from service.errors import NotFoundError
from service.http.api.deps import CtxDep, Limit, Offset, PrincipalDep, RecordId
from service.http.api.models import VerificationOut, VerifyRequest, verification_out
from service.http.api.problems import problem_responses
from service.http.api.qa import resolve_pose
from service.http.audit import audited

router = APIRouter(tags=["verification"])


@router.post(
    "/verify",
    response_model=VerificationOut,
    summary="Error analysis of a newer scan against the current registration (Bai 2018 §3, eq. 10)",
    description=(
        "Predicts every sphere centre of the scan through the current `image_from_robot` from the joints "
        "captured with the scan, compares with the detected centres, and returns the per-sphere errors, "
        "mean / RMS / max (mm) and a histogram PNG (`histogram_url`)."
    ),
    responses=problem_responses(401, 404, 409, 422),
)
async def verify(
    ctx: CtxDep, principal: PrincipalDep, body: Annotated[VerifyRequest | None, Body()] = None
) -> VerificationOut:
    req = body or VerifyRequest()
    qa_check = resolve_pose(ctx, req.qa_protocol_id, req.qa_pose)  # refused before anything runs
    with audited(ctx, principal, "verify", "verification") as note:
        rec = await anyio.to_thread.run_sync(ctx.orchestrator.verify, req.scan_id)
        if qa_check is not None:
            ctx.db.qa.insert_check(replace(qa_check, verification_id=rec.id))
        outcome = "passed" if rec.passed else "failed"
        note(
            rec.id,
            outcome,
            f"registration {rec.registration_id}, scan {rec.scan_id}, max {rec.max_mm:.3f} mm",
        )
    return verification_out(rec)


@router.get(
    "/verifications",
    response_model=list[VerificationOut],
    summary="Every verification, newest first (paginated: limit, offset)",
    responses=problem_responses(401),
)
def list_verifications(ctx: CtxDep, limit: Limit = 100, offset: Offset = 0) -> list[VerificationOut]:
    return [verification_out(r) for r in ctx.db.verifications.list(limit, offset)]


@router.get(
    "/verifications/{verification_id}",
    response_model=VerificationOut,
    summary="One verification",
    responses=problem_responses(401, 404),
)
def get_verification(ctx: CtxDep, verification_id: RecordId) -> VerificationOut:
    rec = ctx.db.verifications.get(verification_id)
    if rec is None:
        raise NotFoundError(f"verification {verification_id} does not exist")
    return verification_out(rec)


@router.get(
    "/verifications/{verification_id}/histogram.png",
    response_class=FileResponse,
    summary="Histogram of the verification's per-sphere errors",
    responses={200: {"content": {"image/png": {}}}, **problem_responses(401, 404)},
)
def histogram(ctx: CtxDep, verification_id: RecordId) -> FileResponse:
    rec = ctx.db.verifications.get(verification_id)
    if rec is None or not rec.histogram_path or not Path(rec.histogram_path).is_file():
        raise NotFoundError(f"verification {verification_id} has no histogram")
    return FileResponse(rec.histogram_path, media_type="image/png")
