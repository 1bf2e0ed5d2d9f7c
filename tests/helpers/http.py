"""One-off plain-HTTP requests for the tests, without a new client (and TLS setup) per call.

``httpx.get`` builds a throwaway ``httpx.Client`` per call, and every client builds a default TLS
context, loading certifi's CA bundle, even for ``http://``: 20 ms of CPU per call against 0.1 ms
through a reused client (measured, httpx 0.29).  A ``/health`` poll every 50 ms while a service
starts spent 40 % of a core on that, which a loaded CI machine takes from the service it waits for
(issue #42 item 8: ~30 s of the suite's CPU).

:func:`get`, :func:`post` and :func:`request` take ``httpx.request``'s arguments and keep its
semantics: each request opens its own connection (nothing is kept alive across calls, so a service
killed and restarted between two probes is reached afresh) through one client per thread.  For
``http://`` URLs only: a TLS test builds its own client with its CA.
"""

from __future__ import annotations

import threading
from typing import Any

import httpx

_local = threading.local()


def _client() -> httpx.Client:
    client = getattr(_local, "client", None)
    if client is None:
        client = httpx.Client(limits=httpx.Limits(max_keepalive_connections=0))
        _local.client = client
    return client


def request(method: str, url: str, **kwargs: Any) -> httpx.Response:
    """``httpx.request`` for a plain-HTTP URL through this thread's client."""
    if not url.startswith("http://"):
        raise ValueError(f"tests.helpers.http is for plain-HTTP URLs, got {url!r}")
    return _client().request(method, url, **kwargs)


def get(url: str, **kwargs: Any) -> httpx.Response:
    return request("GET", url, **kwargs)


def post(url: str, **kwargs: Any) -> httpx.Response:
    return request("POST", url, **kwargs)
