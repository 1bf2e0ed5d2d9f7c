"""The HTTP gate: pure ASGI middleware that admits or refuses a request before the app reads it.

Checked from the request line and headers alone, in this order, before a single body
byte is read (so a 10 MB body without a token costs nothing):

1. ``Host`` must be in the allow-list (``api.allowed_hosts``; default: the bind host, ``localhost``,
   ``127.0.0.1``, ``[::1]`` and the connection's local address, on the service's port) → else 400.
   This closes DNS rebinding: a page on ``evil.example`` that re-points its name at 127.0.0.1
   still sends ``Host: evil.example``.
2. ``Origin``, when present (browsers), must be the service's own (``http(s)://`` + an allowed
   host) or listed in ``api.allowed_origins`` → else 403.  No ``Origin`` header = a non-browser
   client, allowed.
3. Authentication (every path but :data:`PUBLIC_PATHS` — ``/health``, the page ``/``, its
   ``/static/`` assets, ``/favicon.ico`` and the ``/docs`` shell; ``/openapi.json`` included):
   ``Authorization: Bearer <api_token>``, or for ``GET /events`` a single-use ``?ticket=`` from
   ``POST /events/ticket`` (``EventSource`` cannot send headers) → else 401.  ``api.auth =
   "none-loopback-only"`` skips this on a loopback bind (settings refuse it elsewhere).
   Failed authentications are throttled per client address (:class:`AuthThrottle`): after
   ``api.auth_failures_before_throttle`` wrong ``Authorization`` headers the address's wrong tokens
   get 429 with ``Retry-After`` (1 s, doubling per attempt, at most ``api.auth_lockout_max_s``); the
   right token is admitted all the same (tokens carry ≥ 76 bits: the throttle slows and records
   guessing, it must not lock the owner out).  Other addresses are not affected, a request without
   the header is not counted, each burst is one audit entry (action ``auth_throttle``) and at most
   ``api.auth_throttle_audit_rows_per_minute`` such rows are written a minute, then one
   ``auth_throttle_summary`` row.  The address is the socket's: ``X-Forwarded-For`` is believed
   only from the proxies listed in ``api.forwarded_allow_ips`` (none by default).
4. Mutating methods (POST, PUT, PATCH, DELETE) need ``Content-Type: application/json``, bodiless
   ones included → else 415.  A cross-site form or ``fetch`` without a CORS pre-flight can only
   send ``text/plain``, form or multipart bodies, so this closes CSRF.
5. Body size: a ``Content-Length`` above ``api.max_body_bytes`` → 413 at once; a chunked body is
   counted while it is read and refused with 413 as soon as it passes the limit.  Admitted bodies
   are buffered here and replayed to the app.
6. Mutating requests while the database is unusable (file deleted or replaced) → 503.

Every refusal is problem details (RFC 9457): a class of :mod:`service.errors` that states its status
and title (``HostNotAllowedError``, ``UnauthorizedError``, ...), answered through
:mod:`service.error_map` as the routes' errors are.  A refusal that leaves body bytes unread carries
``Connection: close`` so the rest of the body is never parsed.  The gate also guards against bugs:
an exception escaping the app becomes a 500 problem without internals and ``Connection: close``
(the connection ends cleanly instead of being reset on the next request).
"""

from __future__ import annotations

import hashlib
import hmac
import json
import logging
import math
import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal
from urllib.parse import parse_qs

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from registration.errors import OarmRegError
from service.error_map import http_status_of, title_of
from service.errors import (
    AuthThrottledError,
    BadRequestError,
    BodyTooLargeError,
    DatabaseUnavailableError,
    HostNotAllowedError,
    OriginNotAllowedError,
    ReadOnlyTokenError,
    UnauthorizedError,
    UnsupportedMediaTypeError,
)
from service.http.api.problems import problem_kind
from service.http.tickets import TicketBook
from service.logsetup import install_redaction

if TYPE_CHECKING:
    from service.runtime.context import ServiceContext
    from service.settings import ApiSettings, Settings

log = logging.getLogger(__name__)

PROBLEM_MEDIA_TYPE = b"application/problem+json"
TYPE_PREFIX = "urn:oarmreg:problem:"
MUTATING_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})
PUBLIC_PATHS = frozenset({"/health", "/", "/favicon.ico", "/docs"})
"""Paths served without a token: liveness, the page, its favicon and the Swagger UI shell;
they carry no data: the page and /docs sign in and call the data routes with the Bearer token."""
PUBLIC_PREFIXES = ("/static/",)
"""The page's and /docs' assets (``service/http/web/static``, shipped in the wheel)."""
PUBLIC_METHODS = frozenset({"GET", "HEAD"})
EVENTS_PATH = "/events"
READONLY_PREFIX = "readonly:"
"""Principal prefix of the read-only token (``api_readonly_token``): GET only, and event tickets."""
READONLY_POSTS = frozenset({"/events/ticket"})
"""The one POST a read-only token may make: a ticket for the live event stream."""
PRINCIPAL_NO_AUTH = "none-loopback-only"
"""The audit principal when authentication is off (``api.auth = "none-loopback-only"``)."""


def token_principal(token: str) -> str:
    """Who presented ``token``, for the audit log: ``token:`` + 12 hex of its SHA-256 (never the token)."""
    return "token:" + hashlib.sha256(token.encode()).hexdigest()[:12]


def _header(scope: Scope, name: bytes) -> str | None:
    for k, v in scope["headers"]:
        if k == name:
            return str(v.decode("latin-1"))
    return None


def _has_body(scope: Scope) -> bool:
    length = _header(scope, b"content-length")
    return _header(scope, b"transfer-encoding") is not None or (length is not None and length.strip() != "0")


def allowed_hosts(settings: Settings, scope: Scope) -> frozenset[str]:
    """``Host`` values accepted on this connection (lower case, ``name:port``)."""
    server = scope.get("server") or ("127.0.0.1", settings.port)
    port = int(server[1]) if server[1] is not None else settings.port
    out: set[str] = set()
    names = settings.api.allowed_hosts or (settings.host, "localhost", "127.0.0.1", "::1", str(server[0]))
    for name in names:
        name = name.strip().lower()
        bare = name[1:-1] if name.startswith("[") and name.endswith("]") else name
        if ":" in bare and not name.startswith("["):  # an IPv6 literal, or host:port
            if bare.count(":") == 1:
                out.add(bare)
                continue
            name = f"[{bare}]"
        out.add(f"{name}:{port}")
        if port == 80:
            out.add(name)
    return frozenset(out)


def allowed_origins(settings: Settings, hosts: frozenset[str]) -> frozenset[str]:
    """The service's own origins (http(s):// + an allowed host) and those in ``api.allowed_origins``.

    Its own origins always: the status page at ``/`` sends ``Origin`` on its POSTs, and listing a
    navigation UI's origin must not lock the service's own page out.
    """
    own = frozenset(f"{scheme}://{h}" for scheme in ("http", "https") for h in hosts)
    return own | frozenset(o.strip().lower().rstrip("/") for o in settings.api.allowed_origins)


def check_host_origin(settings: Settings, scope: Scope) -> None:
    """Steps 1–2 (Host, Origin); raise :class:`HostNotAllowedError` or :class:`OriginNotAllowedError`."""
    hosts = allowed_hosts(settings, scope)
    host = (_header(scope, b"host") or "").strip().lower()
    if host not in hosts:
        raise HostNotAllowedError(
            f"Host header {host[:100]!r} is not one this service answers to "
            f"({', '.join(sorted(hosts))}); add the name the clients use to api.allowed_hosts"
        )
    origin = _header(scope, b"origin")
    if origin is not None and origin.strip().lower().rstrip("/") not in allowed_origins(settings, hosts):
        raise OriginNotAllowedError(
            f"cross-origin request from {origin[:100]!r} refused; a browser UI served from another "
            "origin must be listed in api.allowed_origins"
        )


def is_public(scope: Scope) -> bool:
    """``GET``/``HEAD`` of :data:`PUBLIC_PATHS` or under :data:`PUBLIC_PREFIXES`; ``/health`` any method."""
    path = str(scope["path"])
    if path == "/health":
        return True
    if scope["method"] not in PUBLIC_METHODS:
        return False
    return path in PUBLIC_PATHS or path.startswith(PUBLIC_PREFIXES)


def token_matches(secret: str, presented: str) -> bool:
    """Does ``presented`` equal the configured ``secret``, in constant time (``hmac.compare_digest``)?"""
    return hmac.compare_digest(presented.strip().encode(), secret.encode())


def bearer_principal(settings: Settings, auth: str) -> str | None:
    """The principal of an ``Authorization`` header value (the API or the read-only token), or None."""
    scheme, _, presented = auth.partition(" ")
    if scheme.lower() != "bearer" or settings.api_token is None:
        return None
    secret = settings.api_token.get_secret_value()
    if token_matches(secret, presented):
        return token_principal(secret)
    if settings.api_readonly_token is not None:
        ro_secret = settings.api_readonly_token.get_secret_value()
        if token_matches(ro_secret, presented):
            return READONLY_PREFIX + token_principal(ro_secret)
    return None


def client_address(scope: Scope) -> str:
    """The client's address as the server saw it (``?`` when the server does not say): the socket's
    peer, or ``X-Forwarded-For`` only when the peer is a proxy in ``api.forwarded_allow_ips``
    (uvicorn rewrites ``scope["client"]`` then; :func:`forwarded_options`)."""
    client = scope.get("client")
    return str(client[0]) if client else "?"


def authenticate(
    ctx: ServiceContext, scope: Scope, book: TicketBook, throttle: AuthThrottle | None = None
) -> str | None:
    """Step 3: the request's principal (None for public paths); raise :class:`UnauthorizedError`, or
    :class:`AuthThrottledError` while ``throttle`` holds the client's address after repeated failures.
    ``book``: the event tickets GET /events may present instead of a token."""
    settings = ctx.settings
    if is_public(scope):
        return None
    if settings.api.auth == "none-loopback-only":
        return PRINCIPAL_NO_AUTH
    auth = _header(scope, b"authorization")
    if auth is not None and auth.strip() and settings.api_token is not None:  # empty: no credentials
        principal = bearer_principal(settings, auth)
        if principal is not None:  # the right token always works, throttled address or not
            return principal
        if throttle is not None:
            address = client_address(scope)
            throttle.check(settings.api, address)  # locked out: 429
            throttle.failed(ctx, address)
        raise UnauthorizedError("the Bearer token does not match the service's api_token")
    if scope["path"] == EVENTS_PATH and scope["method"] == "GET":
        query = parse_qs(scope.get("query_string", b"").decode("latin-1"))
        tickets = query.get("ticket")
        if tickets:
            principal = book.redeem(tickets[0])
            if principal is None:
                raise UnauthorizedError(
                    "the event ticket is unknown, used or expired; POST /events/ticket again"
                )
            return principal
    raise UnauthorizedError(
        "missing 'Authorization: Bearer <token>' header (GET /events also takes ?ticket= from "
        "POST /events/ticket); the API token is set in api_token"
    )


@dataclass
class _Failures:
    """One client address's recent failed authentications."""

    count: int = 0
    first_s: float = 0.0
    last_s: float = 0.0
    locked_until_s: float = 0.0
    refused: int = 0
    """Requests answered 429 in this burst."""
    audited: bool = False


class AuthThrottle:
    """Failed authentications per client address (used on the event loop only).

    The first ``auth_failures_before_throttle`` failures are answered 401 at once; each further
    one locks the address out for ``auth_lockout_initial_s · 2^k`` (at most ``auth_lockout_max_s``),
    during which every wrong token of that address is answered 429 with ``Retry-After`` (the right
    one is admitted before the throttle is asked).  An address without a failure for
    ``auth_failure_memory_s`` starts afresh (a new burst).  Loopback is not exempt.
    """

    MAX_ADDRESSES = 10_000
    """Addresses remembered; the least recently failed are forgotten first (bounded memory)."""

    AUDIT_WINDOW_S = 60.0
    """The window of ``api.auth_throttle_audit_rows_per_minute``, s."""

    def __init__(self, clock: Any = time.monotonic) -> None:
        self._clock = clock
        self._by_address: OrderedDict[str, _Failures] = OrderedDict()
        self._audit_window_start_s = -math.inf
        self._audit_rows = 0
        self._audit_suppressed = 0

    def _current(self, cfg: ApiSettings, address: str, now: float) -> _Failures | None:
        rec = self._by_address.get(address)
        if rec is not None and now - rec.last_s > cfg.auth_failure_memory_s and now >= rec.locked_until_s:
            if rec.audited:
                log.info("auth throttle: burst from %s ended (%d failures, %d answered 429)",
                         address, rec.count, rec.refused)  # fmt: skip
            del self._by_address[address]
            return None
        return rec

    def check(self, cfg: ApiSettings, address: str) -> None:
        """Raise 429 while ``address`` is locked out; a wrong token then counts as one more failure,
        so a guesser that ignores ``Retry-After`` stays locked out."""
        now = self._clock()
        rec = self._current(cfg, address, now)
        if rec is not None and now < rec.locked_until_s:
            self._count(cfg, rec, now)
            raise _throttled(rec.locked_until_s - now)

    def failed(self, ctx: ServiceContext, address: str) -> None:
        """Count a failure of ``address``; raise 429 once it is past the allowance."""
        cfg = ctx.settings.api
        now = self._clock()
        rec = self._current(cfg, address, now)
        if rec is None:
            rec = _Failures(first_s=now)
            self._by_address[address] = rec
            while len(self._by_address) > self.MAX_ADDRESSES:
                self._by_address.popitem(last=False)
        self._by_address.move_to_end(address)
        lock_s = self._count(cfg, rec, now)
        if lock_s is None:
            return
        if not rec.audited:
            rec.audited = True
            self._audit_bounded(ctx, address, rec, lock_s, now)
        raise _throttled(lock_s)

    def _audit_bounded(
        self, ctx: ServiceContext, address: str, rec: _Failures, lock_s: float, now: float
    ) -> None:
        """One row per address per burst, at most ``api.auth_throttle_audit_rows_per_minute`` a minute;
        the first burst past the cap writes one ``auth_throttle_summary`` row, the rest are counted
        (logged when the minute ends) so that spoofed or rotated addresses cannot fill the disk."""
        cap = ctx.settings.api.auth_throttle_audit_rows_per_minute
        if now - self._audit_window_start_s >= self.AUDIT_WINDOW_S:
            if self._audit_suppressed:
                log.warning("auth throttle: %d further throttled addresses in the last minute were not "
                            "audited one by one", self._audit_suppressed)  # fmt: skip
            self._audit_window_start_s, self._audit_rows, self._audit_suppressed = now, 0, 0
        if self._audit_rows < cap:
            self._audit_rows += 1
            self._audit(ctx, address, rec, lock_s)
            return
        self._audit_suppressed += 1
        if self._audit_suppressed == 1:
            detail = (
                f"more than {cap} addresses throttled within {self.AUDIT_WINDOW_S:g} s; further ones in "
                "this minute are counted in the log, not audited one by one "
                "(api.auth_throttle_audit_rows_per_minute)"
            )
            log.warning("auth throttle: %s", detail)
            _record_audit(ctx, "client:*", "auth_throttle_summary", detail)

    @staticmethod
    def _count(cfg: ApiSettings, rec: _Failures, now: float) -> float | None:
        """One more failure; the lock-out it starts (s), None while within the allowance."""
        rec.count += 1
        rec.last_s = now
        beyond = rec.count - cfg.auth_failures_before_throttle
        if beyond <= 0:
            return None
        lock_s = min(cfg.auth_lockout_initial_s * 2.0 ** min(beyond - 1, 64), cfg.auth_lockout_max_s)
        rec.locked_until_s = max(rec.locked_until_s, now + lock_s)
        rec.refused += 1
        return lock_s

    @staticmethod
    def _audit(ctx: ServiceContext, address: str, rec: _Failures, lock_s: float) -> None:
        detail = (
            f"{rec.count} failed authentications from {address} in {rec.last_s - rec.first_s:.1f} s; "
            f"locked out {lock_s:g} s, doubling per further failure up to api.auth_lockout_max_s "
            f"({ctx.settings.api.auth_lockout_max_s:g} s)"
        )
        log.warning("auth throttle: %s", detail)
        _record_audit(ctx, f"client:{address}", "auth_throttle", detail)


def _record_audit(
    ctx: ServiceContext,
    principal: str,
    action: Literal["auth_throttle", "auth_throttle_summary"],
    detail: str,
) -> None:
    try:
        ctx.db.audit.record(principal, action, "api", None, "throttled", detail)
    except Exception as e:  # the refusal matters more than its audit row
        log.error("audit: could not record %s of %s (%s)", action, principal, type(e).__name__)


def _throttled(retry_after_s: float) -> AuthThrottledError:
    wait_s = max(1, math.ceil(retry_after_s))
    return AuthThrottledError(
        f"too many wrong tokens from this address; try again in {wait_s} s (failed authentications are "
        "throttled per address: api.auth_failures_before_throttle, api.auth_lockout_max_s)",
        retry_after_s=wait_s,
    )


def forwarded_options(settings: Settings) -> dict[str, Any]:
    """uvicorn ``Config`` options for forwarded headers: off unless ``api.forwarded_allow_ips`` lists
    the proxies to believe (uvicorn's own default believes 127.0.0.1, so any local process could
    pose as any address and dodge or aim the throttle)."""
    ips = settings.api.forwarded_allow_ips
    return {"proxy_headers": bool(ips), "forwarded_allow_ips": list(ips) if ips else []}


def check_content(settings: Settings, scope: Scope) -> int | None:
    """Steps 4–5 from the headers: refuse non-JSON mutations and declared oversize bodies.

    Returns the declared ``Content-Length`` (None when chunked or absent).
    """
    if scope["method"] in MUTATING_METHODS:
        ctype = (_header(scope, b"content-type") or "").split(";", 1)[0].strip().lower()
        if ctype != "application/json":
            raise UnsupportedMediaTypeError(
                f"{scope['method']} needs 'Content-Type: application/json' (bodiless requests too); "
                f"got {ctype[:60] or 'none'!r}"
            )
    raw = _header(scope, b"content-length")
    if raw is None:
        return None
    if not raw.strip().isdigit() or len(raw.strip()) > 19:
        raise BadRequestError(f"Content-Length {raw[:30]!r} is not a byte count")
    length = int(raw)
    if length > settings.api.max_body_bytes:
        raise _too_large(settings, f"Content-Length {length}")
    return length


def _too_large(settings: Settings, what: str) -> BodyTooLargeError:
    limit = settings.api.max_body_bytes
    return BodyTooLargeError(
        f"{what} exceeds api.max_body_bytes ({limit} bytes); the largest legitimate request "
        "(POST /register with 1000 targets) is well below it"
    )


async def read_body(settings: Settings, receive: Receive) -> tuple[bytes, list[Message]]:
    """Read the whole body, counting bytes; raise 413 as soon as it passes the limit.

    Returns the body and any non-body message seen (``http.disconnect``), to replay.
    """
    limit = settings.api.max_body_bytes
    chunks: list[bytes] = []
    size = 0
    while True:
        message = await receive()
        if message["type"] != "http.request":
            return b"".join(chunks), [message]
        chunk = message.get("body", b"")
        size += len(chunk)
        if size > limit:
            raise _too_large(settings, f"the body (more than {size} bytes so far)")
        chunks.append(chunk)
        if not message.get("more_body", False):
            return b"".join(chunks), []


def replay(body: bytes, extra: list[Message], receive: Receive) -> Receive:
    pending: list[Message] = [{"type": "http.request", "body": body, "more_body": False}, *extra]

    async def _receive() -> Message:
        if pending:
            return pending.pop(0)
        return await receive()

    return _receive


async def send_problem(
    send: Send, status: int, title: str, detail: str, instance: str, *, kind: str,
    close: bool, headers: tuple[tuple[bytes, bytes], ...] = (),
) -> None:  # fmt: skip
    body = json.dumps(
        {"type": TYPE_PREFIX + kind, "title": title, "status": status, "detail": detail, "instance": instance}
    ).encode()
    head = [(b"content-type", PROBLEM_MEDIA_TYPE), (b"content-length", str(len(body)).encode()), *headers]
    if close:
        head.append((b"connection", b"close"))
    await send({"type": "http.response.start", "status": status, "headers": head})
    await send({"type": "http.response.body", "body": body})


class SecurityGate:
    """The gate (see the module docstring); install it as the outermost middleware."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app
        self.throttle = AuthThrottle()
        install_redaction()  # the event ticket in GET /events?ticket= never reaches the access log

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        ctx: ServiceContext = scope["app"].state.ctx
        path = str(scope["path"])[:200]
        try:
            receive = await self._admit(ctx, scope, receive)
        except OarmRegError as e:
            headers = getattr(e, "headers", {})
            await send_problem(
                send,
                http_status_of(e),
                title_of(e),
                str(e),
                path,
                kind=problem_kind(e),
                close=_has_body(scope),
                headers=tuple((k.lower().encode(), v.encode()) for k, v in headers.items()),
            )
            return
        await self._guarded(scope, receive, send, path)

    async def _admit(self, ctx: ServiceContext, scope: Scope, receive: Receive) -> Receive:
        settings = ctx.settings
        check_host_origin(settings, scope)
        principal = authenticate(ctx, scope, scope["app"].state.http.tickets, self.throttle)
        if principal is not None:
            scope.setdefault("state", {})["principal"] = principal
            if (
                principal.startswith(READONLY_PREFIX)
                and scope["method"] in MUTATING_METHODS
                and scope["path"] not in READONLY_POSTS
            ):
                raise ReadOnlyTokenError(
                    "this token (api_readonly_token) can read everything but change nothing; use the "
                    "operator's api_token"
                )
        declared = check_content(settings, scope)
        if scope["method"] in MUTATING_METHODS:
            problem = ctx.db.health_problem()
            if problem is not None:
                raise DatabaseUnavailableError(problem)
        if declared == 0 or not _has_body(scope):
            return receive
        body, extra = await read_body(settings, receive)
        return replay(body, extra, receive)

    async def _guarded(self, scope: Scope, receive: Receive, send: Send, path: str) -> None:
        started = False

        async def _send(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, receive, _send)
        except Exception as exc:
            log.error("unhandled %s on %s %s", type(exc).__name__, scope["method"], path, exc_info=exc)
            if started:
                raise  # mid-response: uvicorn closes the connection
            from service.http.api.problems import INTERNAL_DETAIL

            await send_problem(
                send, 500, "Internal error", INTERNAL_DETAIL, path, kind="internal", close=True
            )
