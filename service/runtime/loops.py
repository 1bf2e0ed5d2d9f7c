"""The service's background loops: each runs as a task until the service stops."""

from __future__ import annotations

import asyncio
import logging

from service.intake.cstore_intake import INTAKE_FOLDER
from service.runtime.context import ServiceContext
from service.store import Database

log = logging.getLogger(__name__)


async def watch_database(db: Database, interval_s: float) -> None:
    """Every ``database.integrity_check_interval_s``: is the database file still the one opened?

    The check also runs on every write transaction and every ``GET /health``; this loop makes a
    vanished file show up in the log (and the rescue copy be taken) even when nothing writes.
    """
    while db.health_problem() is None:
        await asyncio.sleep(interval_s)


async def retention_loop(ctx: ServiceContext) -> None:
    """Run the retention policy at start-up, then every ``retention.interval_s``; never dies."""
    from service.intake.retention import quota_problem, run_retention

    r = ctx.settings.retention
    roots = (ctx.settings.data_dir / INTAKE_FOLDER,)  # C-STORE scans too
    while True:
        try:
            await asyncio.to_thread(
                run_retention, ctx.db, ctx.settings.watch_dir, ctx.bus.publish,
                max_age_days=r.max_age_days, max_disk_mb=r.max_disk_mb, extra_roots=roots,
            )  # fmt: skip
            ctx.retention_problem = await asyncio.to_thread(
                quota_problem, ctx.db, ctx.settings.watch_dir, max_disk_mb=r.max_disk_mb, extra_roots=roots
            )
        except Exception:
            log.exception("retention: the policy run failed; retrying in %.0f s", r.interval_s)
        await asyncio.sleep(r.interval_s)  # a period, not synchronisation
