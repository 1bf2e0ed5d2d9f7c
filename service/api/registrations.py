"""``POST /register``, ``GET /registration/current``, ``GET /registrations[/{id}]``."""

from __future__ import annotations

from typing import Annotated

import anyio.to_thread
from fastapi import APIRouter, Body, Request, Response
from fastapi.responses import JSONResponse

from service.api.deps import CtxDep, Limit, Offset, PrincipalDep, RecordId
from service.api.models import PacsExportOut, RegisterRequest, RegistrationOut, registration_out
from service.api.problems import problem_for, problem_responses
from service.audit import audit_refusal, audited
from service.errors import NoCurrentRegistrationError, NotFoundError
from service.records import RegistrationRefusal

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
        "previous current registration stays current.  `targets_image_mm` are in the IMAGE frame (LPS mm)."
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
    with audited(ctx, principal, "register", "registration") as note:
        rec = await anyio.to_thread.run_sync(ctx.orchestrator.register, req.scan_id, req.targets_image_mm)
        if isinstance(rec, RegistrationRefusal):
            note(rec.registration_id, *audit_refusal(rec.error))
            return problem_for(request, rec.error, registration_id=rec.registration_id)
        note(rec.id, "accepted", f"scan {rec.scan_id}, FRE {rec.fre_mm or 0.0:.3f} mm; made current")
    return registration_out(rec)


@router.get(
    "/registration/current",
    response_model=RegistrationOut,
    summary="The registration the navigation UI should use",
    responses=problem_responses(401, 404),
)
async def current(ctx: CtxDep) -> Response:
    # Usually answered by the app's CurrentRegistrationFastPath; this route documents it and
    # gives the error answers.  Pre-encoded JSON, re-encoded only when the current one changes.
    body = ctx.current_registration_json()
    if body is None:
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
    return [registration_out(r) for r in ctx.db.registrations.list(limit, offset)]


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
    out = registration_out(rec)
    export = ctx.db.pacs_exports.get(registration_id)
    if export is not None:  # its archive to the PACS
        out.pacs_export = PacsExportOut.model_validate(export, from_attributes=True)
    return out
