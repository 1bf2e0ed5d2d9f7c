"""``GET /registrations/{id}/dicom``: the DICOM Spatial Registration object of a registration."""

from __future__ import annotations

from fastapi import APIRouter, Response

from service.api.deps import CtxDep, RecordId
from service.api.problems import problem_responses
from service.errors import NotFoundError

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
    from service.robot_frame import robot_frame_uid
    from service.sro_export import sro_dataset, to_bytes

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
