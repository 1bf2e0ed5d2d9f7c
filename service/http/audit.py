"""Audit trail of the mutating API calls: one ``audit_log`` row per call, success or not.

Usage in a route::

    with audited(ctx, principal, "register", "registration") as note:
        rec = ...                                  # the work; may raise a refusal
        note(rec.id, "accepted", "scan 3, FRE 0.081 mm")

A refusal (an error of the two families) raised in the block is recorded with outcome ``refused``
and its title, then re-raised unchanged; a refusal returned with the id of its stored record
(:class:`service.records.RegistrationRefusal`) is noted with ``note(id, *audit_refusal(error))``.
Failing to write the audit row never hides the answer: it is logged (the database health check
reports why).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from drivers.errors import RobotLinkError
from registration.errors import OarmRegError
from service.error_map import title_of
from service.errors import DatabaseBusyError
from service.runtime.context import ServiceContext
from service.store.audit import AuditAction

log = logging.getLogger(__name__)

Note = Callable[[int | None, str, str], None]


@contextmanager
def audited(ctx: ServiceContext, principal: str, action: AuditAction, target: str) -> Iterator[Note]:
    done: list[tuple[int | None, str, str]] = []

    def note(target_id: int | None, outcome: str, detail: str = "") -> None:
        done.append((target_id, outcome, detail))

    try:
        yield note
    except (OarmRegError, RobotLinkError) as e:
        if isinstance(e, DatabaseBusyError):  # kept in memory, written once the database takes it
            ctx.db.audit.defer(principal, action, target, None, *audit_refusal(e))
        else:
            _write(ctx, principal, action, target, None, *audit_refusal(e))
        raise
    except Exception as e:
        _write(ctx, principal, action, target, None, "error", type(e).__name__)
        raise
    for target_id, outcome, detail in done:
        _write(ctx, principal, action, target, target_id, outcome, detail)


def audit_refusal(e: OarmRegError | RobotLinkError) -> tuple[str, str]:
    """The (outcome, detail) of an audit row for refusal ``e``."""
    return "refused", title_of(e)


def _write(
    ctx: ServiceContext, principal: str, action: AuditAction, target: str, target_id: int | None,
    outcome: str, detail: str,
) -> None:  # fmt: skip
    try:
        ctx.db.audit.record(principal, action, target, target_id, outcome, detail)
    except Exception as e:  # the answer matters more than its audit row
        log.error(
            "audit: could not record %s %s %s by %s (%s)",
            action,
            target,
            outcome,
            principal,
            type(e).__name__,
        )
