"""``POST /register``, ``GET /registration/current``, ``GET /registrations[/{id}]``."""

from __future__ import annotations

import json
from typing import Annotated

import anyio.to_thread
from fastapi import APIRouter, Body, Request, Response
from fastapi.responses import JSONResponse

from service.errors import NoCurrentRegistrationError, NotFoundError, SupersededScanError
from service.http.api.deps import CtxDep, HttpDep, Limit, Offset, PrincipalDep, RecordId
from service.http.api.models import (
    PacsExportOut,
    RegisterRequest,
    RegistrationOut,
    WithdrawalOut,
    registration_out,
)
from service.http.api.problems import problem_for, problem_responses
from service.http.audit import audit_refusal, audited
from service.records import RegistrationRefusal
from service.registrations.orchestrator import SupersededOverride

router = APIRouter(tags=["registration"])


@router.post(
    "/register",
    response_model=RegistrationOut,
    summary="Register the latest (or given) scan: load → MAR → detect → register",
    description=(
        "Runs the pipeline on the scan's DICOM series with the joint angles captured when it arrived, "
        "stores the result and makes it current if every quality gate passes.  A refusal (robot moved, "
        "robot link down, too few spheres, ambiguous correspondence, FRE over the gate) answers 409, an "
        "unusable scan 422, both as problem details carrying `registration_id` of the stored refusal; the "
        "previous current registration stays current.  `targets_image_mm` are in the IMAGE frame (LPS mm).  "
        "A scan the service has newer evidence against (a newer scan at the same FrameOfReferenceUID "
        "with an accepted registration or a failed verification, or a verification withdrew this scan's "
        "registration) is refused 409 naming the newer scan (`newer_scan_id`), unless the body says "
        '`allow_superseded: true` with a `reason` (audited): docs/safety.md, "Which registration may '
        'be current".'
    ),
    responses=problem_responses(401, 404, 409, 422),
)
async def register(
    request: Request,
    ctx: CtxDep,
    principal: PrincipalDep,
    body: Annotated[RegisterRequest | None, Body()] = None,
) -> RegistrationOut | JSONResponse:
    req = body or RegisterRequest()
    override = SupersededOverride((req.reason or "").strip()) if req.allow_superseded else None
    with audited(ctx, principal, "register", "registration") as note:
        rec = await anyio.to_thread.run_sync(
            lambda: ctx.orchestrator.register(
                req.scan_id, req.targets_image_mm, override=override, phantom_confirmed=req.phantom_confirmed
            )
        )
        if isinstance(rec, RegistrationRefusal):
            note(rec.registration_id, *audit_refusal(rec.error))
            return _refusal(request, rec)
        note(rec.id, "accepted", f"scan {rec.scan_id}, FRE {rec.fre_mm or 0.0:.3f} mm; made current")
        over = rec.figures.provenance.get("superseded_override") if rec.figures is not None else None
        if isinstance(over, dict):  # the explicit override, audited on its own row
            note(
                rec.id,
                "superseded-override",
                f"allow_superseded: {over['detail']}; made current anyway, reason: {over['reason']}",
            )
    return registration_out(rec)


def _refusal(request: Request, rec: RegistrationRefusal) -> JSONResponse:
    """The refusal's problem details; a superseded scan's names the newer scan (``newer_scan_id``)."""
    e = rec.error
    answer = problem_for(request, e, registration_id=rec.registration_id)
    if not isinstance(e, SupersededScanError):
        return answer
    body = json.loads(bytes(answer.body))
    body.update(newer_scan_id=e.newer_scan_id, rule=e.rule)
    return JSONResponse(body, status_code=answer.status_code, media_type=answer.media_type)


@router.get(
    "/registration/current",
    response_model=RegistrationOut,
    summary="The registration the navigation UI should use",
    description=(
        "409 when nothing is current.  When a verification withdrew the registration, the problem "
        "details name it: `registration_id`, `verification_id` (null: it could not be computed), "
        "`verification_scan_id`, `likely_cause` (cell-not-calibrated | phantom-or-oarm-moved), `action`."
    ),
    responses=problem_responses(401, 404, 409),
)
async def current(request: Request, ctx: CtxDep, http: HttpDep) -> Response:
    # Usually answered by the app's CurrentRegistrationFastPath; this route documents it and
    # gives the error answers.  Pre-encoded JSON, re-encoded only when the current one changes.
    body = http.current_registration_json(ctx.orchestrator.current)
    if body is None:
        w = ctx.orchestrator.withdrawal
        if w is not None:
            err = NoCurrentRegistrationError(f"no current registration: {w.describe()}; {w.action}")
            answer = problem_for(request, err, registration_id=w.registration_id)
            problem = json.loads(bytes(answer.body))
            problem["withdrawal"] = WithdrawalOut.model_validate(w, from_attributes=True).model_dump()
            problem.update(
                verification_id=w.verification_id, verification_scan_id=w.verification_scan_id,
                likely_cause=w.likely_cause, action=w.action,
            )  # fmt: skip
            return JSONResponse(problem, status_code=answer.status_code, media_type=answer.media_type)
        withdrawn = ctx.orchestrator.no_current_reason
        if withdrawn:
            raise NoCurrentRegistrationError(f"no current registration: {withdrawn}; POST /register again")
        raise NoCurrentRegistrationError("no registration has been accepted yet; POST /register after a scan")
    return Response(body, media_type="application/json")


@router.get(
    "/registrations",
    response_model=list[RegistrationOut],
    summary="Every registration, newest first",
    responses=problem_responses(401),
)
def list_registrations(
    ctx: CtxDep,
    limit: Limit = 100,
    offset: Offset = 0,
) -> list[RegistrationOut]:
    return [
        registration_out(ctx.orchestrator.with_evidence(r)) for r in ctx.db.registrations.list(limit, offset)
    ]


@router.get(
    "/registrations/{registration_id}",
    response_model=RegistrationOut,
    summary="One registration",
    responses=problem_responses(401, 404),
)
def get_registration(ctx: CtxDep, registration_id: RecordId) -> RegistrationOut:
    rec = ctx.db.registrations.get(registration_id)
    if rec is None:
        raise NotFoundError(f"registration {registration_id} does not exist; GET /registrations lists them")
    out = registration_out(ctx.orchestrator.with_evidence(rec))
    export = ctx.db.pacs_exports.get(registration_id)
    if export is not None:  # its archive to the PACS
        out.pacs_export = PacsExportOut.model_validate(export, from_attributes=True)
    return out
