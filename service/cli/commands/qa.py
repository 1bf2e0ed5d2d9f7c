"""``oarmreg qa protocol create|list``: QA protocols (named sets of verification poses)
in the service's database, the same as ``POST /qa/protocols`` / ``GET /qa/protocols``.

Safe while the service runs (SQLite WAL; the service's shared lock is taken like ``backup``).
A refused protocol (bad pose, name taken) exits 4 with the reason; the audit log names ``cli``.
"""

from __future__ import annotations

import argparse
import json
import sys

from service.cli.commands.argtypes import add_data_arguments, db_path_from_args

HELP = "QA protocols: named sets of verification poses (create, list)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="qa_what", metavar="WHAT", required=True)
    proto = sub.add_parser("protocol", help="QA protocols", description="QA protocols")
    actions = proto.add_subparsers(dest="qa_action", metavar="ACTION", required=True)
    create = actions.add_parser("create", help="store a new protocol", description="store a new protocol")
    create.add_argument("name", help="the protocol's name (never reused)")
    create.add_argument(
        "--pose",
        action="append",
        required=True,
        metavar="NAME=J1,J2,J3,J4,J5,J6",
        help="one pose: its name and six joint angles (rad; --degrees for degrees); repeat per pose",
    )
    create.add_argument("--degrees", action="store_true", help="the joint angles are in degrees")
    create.add_argument("--description", default="", help="when and how the protocol is run")
    add_data_arguments(create)
    listing = actions.add_parser("list", help="every protocol as JSON", description="every protocol as JSON")
    add_data_arguments(listing)


def _poses(specs: list[str], degrees: bool) -> list[dict[str, object]]:
    import math

    from service.errors import QaProtocolError

    out: list[dict[str, object]] = []
    for spec in specs:
        name, sep, values = spec.partition("=")
        try:
            joints = [float(v) for v in values.split(",")] if sep else []
        except ValueError:
            joints = []
        if not sep or not joints:
            raise QaProtocolError(f"--pose {spec!r}: write NAME=J1,J2,J3,J4,J5,J6 (numbers, comma-separated)")
        out.append({"name": name.strip(), "joints_rad": [math.radians(q) if degrees else q for q in joints]})
    return out


def run(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    from service.errors import QaProtocolError, QaProtocolNameTakenError
    from service.http.api.qa import QaProtocolIn, protocol_out
    from service.store import Database
    from service.store.qa import QaPose

    db = Database.open(db_path_from_args(args))
    try:
        if args.qa_action == "list":
            rows = [protocol_out(p).model_dump() for p in db.qa.list_protocols(limit=1000)]
            sys.stdout.write(json.dumps(rows, indent=2) + "\n")
            return 0
        try:
            body = QaProtocolIn(
                name=args.name, description=args.description, poses=_poses(args.pose, args.degrees)
            )
        except ValidationError as e:
            why = "; ".join(f"{'.'.join(map(str, err['loc']))}: {err['msg']}" for err in e.errors())
            raise QaProtocolError(f"protocol {args.name!r} refused: {why}") from None
        if db.qa.find_by_name(body.name) is not None:
            raise QaProtocolNameTakenError(
                f"a QA protocol named {body.name!r} exists already; protocols are not edited: "
                "choose a new name"
            )
        poses = tuple(QaPose(p.name, tuple(p.joints_rad)) for p in body.poses)
        new_id = db.qa.insert_protocol(body.name, body.description, poses)
        db.audit.record(
            "cli",
            "qa_protocol_create",
            "qa_protocol",
            new_id,
            "created",
            f"{body.name!r}, {len(poses)} poses",
        )
        sys.stdout.write(f"QA protocol {new_id} {body.name!r} stored with {len(poses)} poses\n")
        return 0
    finally:
        db.close()
