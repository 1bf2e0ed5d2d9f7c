"""``GET /audit``: who registered, verified, activated or deleted what (newest first)."""

from __future__ import annotations

from fastapi import APIRouter

from service.http.api.deps import CtxDep, Limit, Offset
from service.http.api.models import AuditOut
from service.http.api.problems import problem_responses

router = APIRouter(tags=["audit"])


@router.get(
    "/audit",
    response_model=list[AuditOut],
    summary="The audit log, newest first",
    description="`principal` is `token:` + 12 hex of the token's SHA-256 (never the token itself).",
    responses=problem_responses(401),
)
def audit_log(ctx: CtxDep, limit: Limit = 100, offset: Offset = 0) -> list[AuditOut]:
    return [AuditOut.model_validate(e, from_attributes=True) for e in ctx.db.audit.list(limit, offset)]
