"""Browser hardening headers on every HTTP answer (pure ASGI).

``Content-Security-Policy: default-src 'self'`` everywhere: the page loads nothing from another
origin and runs no inline script or style, so an injected ``<script>`` in a record's text could
not run.  ``/docs`` alone also allows ``data:`` images (Swagger UI's stylesheet draws its icons as
``data:`` SVG); it loads no script from elsewhere either.
"""

from __future__ import annotations

from starlette.types import ASGIApp, Message, Receive, Scope, Send

PAGE_CSP = "default-src 'self'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'"
DOCS_CSP = PAGE_CSP + "; img-src 'self' data:"
COMMON: tuple[tuple[bytes, bytes], ...] = (
    (b"x-content-type-options", b"nosniff"),
    (b"referrer-policy", b"no-referrer"),
    (b"x-frame-options", b"DENY"),
)


def csp_for(path: str) -> str:
    return DOCS_CSP if path == "/docs" else PAGE_CSP


class SecurityHeaders:
    """Adds the CSP and :data:`COMMON` to every ``http.response.start`` that lacks them."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        extra = ((b"content-security-policy", csp_for(str(scope["path"])).encode()), *COMMON)

        async def _send(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = list(message.get("headers", []))
                present = {k.lower() for k, _ in headers}
                headers.extend((k, v) for k, v in extra if k not in present)
                message = {**message, "headers": headers}
            await send(message)

        await self.app(scope, receive, _send)
