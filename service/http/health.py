"""What is wrong with the running service: one list of typed problems for ``GET /status`` and
``GET /ready`` (``GET /health`` stays liveness plus the database).

Each problem source is a function ``(ctx) -> list[HealthProblem]`` in :data:`PROBLEM_SOURCES`; a new
source is one function appended to that list.  The problem types and what each means are listed in
docs/safety.md ("Stillness and health").
"""

from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from service.http.state import HttpState
    from service.runtime.context import ServiceContext

PROBE_BYTES = 4096
"""Size of the file the data-folder probe writes (one filesystem block: a full disk refuses it)."""


@dataclass(frozen=True)
class HealthProblem:
    """One reason the service is unhealthy.

    ``type`` is stable (``urn:oarmreg:health:<type>``, docs/safety.md); ``title`` short; ``detail``
    says what happened and what to do.
    """

    type: str
    title: str
    detail: str

    def __str__(self) -> str:
        return f"{self.title}: {self.detail}"


def database_problems(ctx: ServiceContext) -> list[HealthProblem]:
    p = ctx.db.health_problem()
    return [] if p is None else [HealthProblem("database-unavailable", "Database unavailable", p)]


def robot_link_problems(ctx: ServiceContext) -> list[HealthProblem]:
    p = ctx.capture.problem()
    return [] if p is None else [HealthProblem("robot-link-down", "Robot link down", p)]


def watcher_problems(ctx: ServiceContext) -> list[HealthProblem]:
    w = ctx.watcher
    if w is None:
        return []
    health, why = w.health()
    if health == "ok":
        return []
    kind = "watcher-stopped" if health == "stopped" else f"watcher-{health}"
    return [HealthProblem(kind, f"Folder watcher {health}", f"{w.watch_dir}: {why}")]


def listener_problems(ctx: ServiceContext) -> list[HealthProblem]:
    """An enabled DICOM SCP or OpenIGTLink server that is not listening."""
    out: list[HealthProblem] = []
    s = ctx.settings
    scp = ctx.cstore.scp if ctx.cstore is not None else None
    igtl = ctx.igtl.server if ctx.igtl is not None else None
    for name, enabled, server, what in (
        ("dicom", s.dicom.enabled, scp, "the O-arm cannot send scans by C-STORE"),
        ("igtl", s.igtl.enabled, igtl, "navigation receives no OpenIGTLink transforms"),
    ):
        if not enabled:
            continue
        port: int | None = None
        if server is not None:
            with contextlib.suppress(RuntimeError, AttributeError, OSError):
                port = int(server.port)
        if port is None:
            out.append(
                HealthProblem(
                    "listener-stopped",
                    "Listener stopped",
                    f"the {'DICOM C-STORE SCP' if name == 'dicom' else 'OpenIGTLink server'} is enabled "
                    f"but not listening: {what}; see the log, then restart the service",
                )
            )
    return out


def data_dir_problems(ctx: ServiceContext) -> list[HealthProblem]:
    """Write (and remove) a small file in the data folder: a folder that refuses it cannot keep records."""
    folder = ctx.settings.data_dir
    probe = folder / f".health-probe-{secrets.token_hex(4)}"
    try:
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        try:
            os.write(fd, b"\0" * PROBE_BYTES)
        finally:
            os.close(fd)
    except OSError as e:
        return [
            HealthProblem(
                "data-dir-unwritable",
                "Data folder refuses writes",
                f"{folder} refuses writes ({e.strerror or e}); registrations and scans cannot be stored: "
                "free space or fix the folder's permissions",
            )
        ]
    finally:
        with contextlib.suppress(OSError):
            probe.unlink()
    return []


def intake_write_problems(ctx: ServiceContext) -> list[HealthProblem]:
    """The C-STORE intake could not write the last instance it received (its folder may be a mount
    of its own, so the data-folder probe does not see it); cleared by the next instance stored."""
    why = None if ctx.cstore is None else ctx.cstore.scp.write_failure
    if why is None:
        return []
    return [
        HealthProblem(
            "intake-unwritable",
            "C-STORE intake refuses writes",
            f"the DICOM intake answers 0xA700 (out of resources): {why}; the O-arm's scans are not "
            "stored until space is freed there, then send the series again",
        )
    ]


def intake_association_problems(ctx: ServiceContext) -> list[HealthProblem]:
    """The C-STORE intake refused or failed an association for its own reasons (every
    ``dicom.maximum_associations`` slot taken, ``accept`` failing, a transport error);
    cleared by the next association released normally.  Counters: ``listeners.dicom.counters``."""
    why = None if ctx.cstore is None else ctx.cstore.scp.association_failure
    if why is None:
        return []
    return [HealthProblem("intake-refusing", "C-STORE intake refusing associations", why)]


def retention_problems(ctx: ServiceContext) -> list[HealthProblem]:
    """Retention could not bring the scan folders under ``retention.max_disk_mb``."""
    p = ctx.retention_problem
    return [] if p is None else [HealthProblem("retention-over-quota", "Retention over quota", p)]


def qa_drift_problems(ctx: ServiceContext) -> list[HealthProblem]:
    """The QA drift rule (:mod:`service.registrations.qa_drift`) over the checks under the active
    calibration."""
    from service.registrations.qa_drift import drift

    q = ctx.settings.qa
    cal_id = ctx.db.calibrations.active_id()
    means = ctx.db.qa_trend.last_means(cal_id, q.drift_window)
    verdict = drift(means, window=q.drift_window, limit_mm=q.drift_mean_mm, rise_mm=q.drift_rise_mm)
    if verdict is None:
        return []
    under = "the nominal robot model" if cal_id is None else f"calibration {cal_id}"
    return [
        HealthProblem(
            "qa-drift",
            "Recalibrate: QA drifting",
            f"under {under}, {verdict.describe()}; the cell is drifting from its calibration: run a "
            "calibration session (docs/calibration.md) and activate it, then repeat the QA protocol "
            "(GET /qa/trend shows the series)",
        )
    ]


def bus_listener_problems(ctx: ServiceContext) -> list[HealthProblem]:
    """A safety listener of the event bus (:mod:`service.event_bus`) whose last call raised."""
    return [
        HealthProblem(
            "safety-listener-failing",
            "Safety listener failing",
            f"{f.describe()}: its safety duty (telling navigation of a registration change) may be "
            "undone; compare what navigation shows with GET /registration/current, see the log for the "
            "traceback; cleared by the listener's next successful call (e.g. the next registration)",
        )
        for f in ctx.bus.failing_safety_listeners()
    ]


def registration_withdrawn_problems(ctx: ServiceContext) -> list[HealthProblem]:
    """A verification withdrew the registration and nothing has been made current since: navigation
    has no registration it may use (docs/safety.md, "Which registration may be current")."""
    w = ctx.orchestrator.withdrawal
    if w is None:
        return []
    return [
        HealthProblem(
            "registration-withdrawn",
            "Registration withdrawn by a failed verification",
            f"{w.describe()}; {w.action}",
        )
    ]


def robot_settings_problems(ctx: ServiceContext) -> list[HealthProblem]:
    """The robot settings changed since what was made with them (docs/safety.md, "Robot settings bind
    what was made with them"): the current registration withdrawn at start-up, while nothing is current;
    an active calibration not used."""
    out = []
    why = ctx.orchestrator.robot_side_withdrawal
    if why and ctx.orchestrator.current is None:
        out.append(
            HealthProblem("robot-settings-changed", "Registration made under other robot settings", why)
        )
    if ctx.calibrations.inactive_reason:
        out.append(
            HealthProblem(
                "calibration-not-used",
                "Calibration made under other robot settings",
                ctx.calibrations.inactive_reason,
            )
        )
    return out


IGTL_REFUSAL_HOLD_S = 60.0
"""An OpenIGTLink refusal stays a health problem this long, s: a navigation client refused once (it
retries, or its user gives up) is seen on the next minute's status checks, not only at that instant."""


def igtl_slot_problems(ctx: ServiceContext) -> list[HealthProblem]:
    """The OpenIGTLink listener at ``igtl.max_clients`` or refusing connections (full, or an address at
    its ``igtl.max_clients_per_address`` share) within :data:`IGTL_REFUSAL_HOLD_S`: a navigation client
    that connects gets EOF."""
    server = ctx.igtl.server if ctx.igtl is not None else None
    if server is None:
        return []
    r = server.slot_report()
    held = ", ".join(f"{host} {n}" for host, n in list(r.by_address.items())[:4]) or "none"
    out: list[HealthProblem] = []
    full_recent = r.full_refused_s_ago is not None and r.full_refused_s_ago < IGTL_REFUSAL_HOLD_S
    if r.clients >= r.max_clients or full_recent:
        refused = (
            f"; it refused {r.full_refused_host} {r.full_refused_s_ago:.0f} s ago"
            if full_recent and r.full_refused_s_ago is not None
            else ""
        )
        out.append(
            HealthProblem(
                "igtl-full",
                "OpenIGTLink listener full",
                f"{r.clients} of igtl.max_clients = {r.max_clients} connections held (by address: {held})"
                f"{refused}; a navigation client that connects now is closed at once: close the unused "
                "OpenIGTLink clients (GET /status, listeners.igtl.peers) or raise igtl.max_clients",
            )
        )
    ago = r.address_refused_s_ago
    if ago is not None and ago < IGTL_REFUSAL_HOLD_S:
        host = r.address_refused_host
        out.append(
            HealthProblem(
                "igtl-address-share",
                "OpenIGTLink address at its share",
                f"{host} was refused a connection {ago:.0f} s ago: it holds {r.by_address.get(host, 0)} of "
                f"its igtl.max_clients_per_address = {r.address_share}; close that host's idle OpenIGTLink "
                "connections or raise its share (other hosts still connect)",
            )
        )
    return out


def http_slot_problems(http: HttpState | None) -> list[HealthProblem]:
    """HTTP connections closed within :data:`IGTL_REFUSAL_HOLD_S` because their address held its
    ``api.max_connections_per_address`` share or their peer read nothing for ``api.write_timeout_s``."""
    import time

    c = None if http is None else http.limits
    if c is None or time.monotonic() - c.last_drop_at >= IGTL_REFUSAL_HOLD_S:
        return []
    ago = time.monotonic() - c.last_drop_at
    return [
        HealthProblem(
            "http-peer-limits",
            "HTTP connections closed for holding slots",
            f"{c.last_address or 'a peer'} had a connection closed {ago:.0f} s ago (since start-up: "
            f"{c.address_share} over an address's api.max_connections_per_address share, "
            f"{c.write_timeouts} whose peer read nothing for api.write_timeout_s): a host holds HTTP "
            "connections without reading them; find and stop that client (other hosts are still served)",
        )
    ]


PROBLEM_SOURCES: list[Callable[[ServiceContext], list[HealthProblem]]] = [
    database_problems,
    robot_link_problems,
    watcher_problems,
    listener_problems,
    data_dir_problems,
    intake_write_problems,
    intake_association_problems,
    retention_problems,
    qa_drift_problems,
    bus_listener_problems,
    registration_withdrawn_problems,
    robot_settings_problems,
    igtl_slot_problems,
]
"""Every problem source of the service's parts, in the order their problems are listed (then HTTP's
own, :func:`http_slot_problems`).  Append new ones here."""


def collect_problems(ctx: ServiceContext, http: HttpState | None = None) -> list[HealthProblem]:
    """Every current problem (empty: healthy): the service's parts', then the HTTP door's."""
    out: list[HealthProblem] = []
    for source in PROBLEM_SOURCES:
        out.extend(source(ctx))
    out.extend(http_slot_problems(http))
    return out
