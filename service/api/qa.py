"""``POST /qa/protocols``, ``GET /qa/protocols`` (paginated), ``GET /qa/protocols/{id}``.

A QA protocol is a named set of verification poses, so successive QA checks of a cell are
comparable; ``POST /verify`` names one with ``qa_protocol_id`` and ``qa_pose``.
"""

from __future__ import annotations

import math
from typing import Annotated

from fastapi import APIRouter
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from service.api.deps import CtxDep, Limit, Offset, PrincipalDep, RecordId
from service.api.problems import problem_responses
from service.audit import audited
from service.context import ServiceContext
from service.errors import NotFoundError, QaProtocolError, QaProtocolNameTakenError
from service.store.qa import QaCheck, QaPose, QaProtocol

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
