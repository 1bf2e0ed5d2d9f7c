"""The HTTP side: the app factory and its lifespan, the API routers, the status page, authentication,
TLS, SSE tickets and health/readiness.

Enters: HTTP requests (navigation UI, OR staff, scripts).
Leaves: problem-details JSON and records as JSON, the page, server-sent events.
"""
