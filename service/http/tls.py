"""HTTPS for the REST API: uvicorn's ``ssl_certfile`` / ``ssl_keyfile`` from ``[tls]``.

The settings refuse a non-loopback bind without a token, and without TLS unless
``tls.allow_insecure_http = true`` (a TLS-terminating proxy in front).  The certificate and key
are PEM files; an unreadable or mismatched pair fails at start-up (:class:`TlsConfigError`).
"""

from __future__ import annotations

import ssl
from typing import Any

from service.errors import TlsConfigError
from service.settings import Settings


def uvicorn_ssl_options(settings: Settings) -> dict[str, Any]:
    """``{"ssl_certfile": ..., "ssl_keyfile": ...}`` for :class:`uvicorn.Config` ({} without TLS).

    Raises
    ------
    TlsConfigError
        The pair does not load (not PEM, key does not match the certificate, encrypted key).
    """
    t = settings.tls
    if t.cert_file is None or t.key_file is None:
        return {}
    try:
        ssl.create_default_context(ssl.Purpose.CLIENT_AUTH).load_cert_chain(t.cert_file, t.key_file)
    except (ssl.SSLError, OSError) as e:
        raise TlsConfigError(
            f"tls.cert_file {t.cert_file} / tls.key_file {t.key_file} cannot be loaded ({e}); expected a PEM "
            "certificate (chain) and its unencrypted PEM private key"
        ) from None
    return {"ssl_certfile": str(t.cert_file), "ssl_keyfile": str(t.key_file)}


def scheme(settings: Settings) -> str:
    return "https" if settings.tls.enabled else "http"
