"""``GET /registrations/{id}/dicom``: the DICOM Spatial Registration object of a registration."""

from __future__ import annotations

from fastapi import APIRouter, Response

from service.errors import NotFoundError, PacsExportError
from service.http.api.deps import CtxDep, PrincipalDep, RecordId
from service.http.api.models import PacsExportOut
from service.http.api.problems import problem_responses
from service.http.audit import audited

router = APIRouter(tags=["registration"])

DICOM_MEDIA_TYPE = "application/dicom"


@router.get(
    "/registrations/{registration_id}/dicom",
    summary="The registration as a DICOM Spatial Registration object (application/dicom)",
    description=(
        "A Part-10 Spatial Registration object (SOP Class 1.2.840.10008.5.1.4.1.1.66.1).  Its Frame of "
        "Reference is the scan's; item 1 of the Registration Sequence is the scan's frame (identity, its "
        "slices referenced), item 2 the robot base frame (its UID minted once per data folder) with "
        "`image_from_robot`, row-major, robot mm → image DICOM LPS mm.  409 for a refused registration "
        "or one whose scan's instance UIDs were not stored."
    ),
    response_class=Response,
    responses={200: {"content": {DICOM_MEDIA_TYPE: {}}}, **problem_responses(401, 404, 409)},
)
def registration_dicom(ctx: CtxDep, registration_id: RecordId) -> Response:
    from service.navigation.sro_export import sro_dataset, to_bytes
    from service.registrations.robot_frame import robot_frame_uid

    rec = ctx.db.registrations.get(registration_id)
    if rec is None:
        raise NotFoundError(f"registration {registration_id} does not exist; GET /registrations lists them")
    inst = ctx.db.scan_instances.get(rec.series_uid) if rec.series_uid else None
    cur = ctx.orchestrator.current
    ds = sro_dataset(
        rec,
        inst,
        robot_frame_uid=robot_frame_uid(ctx.settings.data_dir),
        is_current=cur is not None and cur.id == rec.id,
    )
    return Response(
        to_bytes(ds),
        media_type=DICOM_MEDIA_TYPE,
        headers={"Content-Disposition": f'attachment; filename="registration-{registration_id}-sro.dcm"'},
    )


@router.post(
    "/registrations/{registration_id}/pacs-export",
    response_model=PacsExportOut,
    summary="Send the registration's Spatial Registration object to the PACS again",
    description=(
        "Queues the archive of an accepted registration now, its attempts reset: after a PACS refused "
        "it (`failed` with the PACS's status) and the PACS was fixed, or to skip the back-off wait of a "
        "`pending` one.  Also queues a registration accepted before the PACS was configured.  409 when no "
        "PACS is configured (`[pacs] host`), for a refused or withdrawn registration, or one already `sent`."
    ),
    responses=problem_responses(401, 404, 409),
)
def retry_pacs_export(ctx: CtxDep, principal: PrincipalDep, registration_id: RecordId) -> PacsExportOut:
    with audited(ctx, principal, "pacs_export", "registration") as note:
        rec = ctx.db.registrations.get(registration_id)
        if rec is None:
            raise NotFoundError(
                f"registration {registration_id} does not exist; GET /registrations lists them"
            )
        exporter = ctx.pacs
        if exporter is None:
            raise PacsExportError(
                "no PACS is configured: set [pacs] host, port and ae_title (env OARMREG_PACS__HOST)"
            )
        if rec.status not in ("accepted", "retired") or rec.image_from_robot is None:
            raise PacsExportError(
                f"registration {registration_id} is {rec.status}: only an accepted registration is archived"
            )
        row = ctx.db.pacs_exports.get(registration_id)
        if row is not None and row.state == "sent":
            raise PacsExportError(
                f"registration {registration_id} was already archived to {row.destination} ({row.reason})"
            )
        if row is None:
            exporter.enqueue(registration_id)
        else:
            exporter.retry(registration_id)
        note(registration_id, "queued", f"to {exporter.destination}")
        new = ctx.db.pacs_exports.get(registration_id)
        assert new is not None
        return PacsExportOut.model_validate(new, from_attributes=True)
