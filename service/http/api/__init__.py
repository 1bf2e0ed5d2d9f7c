"""HTTP API: one router per resource, assembled by :func:`service.http.app.create_app`."""
