"""HTTP API: one router per resource, assembled by :func:`service.app.create_app`."""
