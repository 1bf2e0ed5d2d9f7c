"""``GET /scans`` and ``GET /scans/{id}``."""

from __future__ import annotations

from fastapi import APIRouter

from service.errors import NotFoundError
from service.http.api.deps import CtxDep, Limit, Offset, RecordId
from service.http.api.models import ScanOut, scan_out
from service.http.api.problems import problem_responses

router = APIRouter(tags=["scans"])


@router.get(
    "/scans",
    response_model=list[ScanOut],
    summary="Recorded scans, newest first",
    responses=problem_responses(401),
)
def list_scans(
    ctx: CtxDep,
    limit: Limit = 100,
    offset: Offset = 0,
) -> list[ScanOut]:
    return [scan_out(s) for s in ctx.db.scans.list(limit, offset)]


@router.get(
    "/scans/{scan_id}",
    response_model=ScanOut,
    summary="One scan with its joint snapshot",
    responses=problem_responses(401, 404),
)
def get_scan(ctx: CtxDep, scan_id: RecordId) -> ScanOut:
    scan = ctx.db.scans.get(scan_id)
    if scan is None:
        raise NotFoundError(f"scan {scan_id} does not exist; GET /scans lists the recorded scans")
    return scan_out(scan)
