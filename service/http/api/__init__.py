"""HTTP API: one router per resource, assembled by :func:`service.http.app.create_app`.

Enters: HTTP requests that passed the gate (:mod:`service.http.security`), with the
:class:`~service.runtime.context.ServiceContext`.
Leaves: records as JSON (:mod:`service.http.api.models`), problem details for every refusal.
"""
