"""The OR's status / QA page and the self-hosted API docs.

Everything here is same-origin and shipped in the wheel (``service/http/web/static``): no CDN, no
build step.  :mod:`service.http.web.routes` serves the page at ``/``, its assets under ``/static/``,
the favicon and the Swagger UI shell at ``/docs``; these are the only public paths besides
``/health`` (:data:`service.http.security.PUBLIC_PATHS`).  :mod:`service.http.web.headers` adds the
Content-Security-Policy (``default-src 'self'``) to every answer, and :func:`service.http.web.cors`
installs Starlette's CORSMiddleware for the origins listed in ``api.allowed_origins``.

Enters: browser requests for ``/``, ``/static/*`` and ``/docs``.
Leaves: the page, its assets and the Swagger UI shell, with their security headers.
"""
