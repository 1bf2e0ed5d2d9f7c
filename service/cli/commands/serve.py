"""``oarmreg serve``: run the registration service (uvicorn).

Settings: ``--config FILE`` (TOML), then ``OARMREG_*`` environment variables, then the flags
below (highest precedence).  See ``configs/oarmreg.toml``.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import socket
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

HELP = "run the registration service (REST API, DICOM watcher, robot link)"
DEFAULT_LOG_LEVEL = logging.INFO
"""The start-up line (every listener, the data folder) shows by default; ``[log] level`` changes it."""

log = logging.getLogger(__name__)

SERVER_START_TIMEOUT_S = 30.0
"""How long :func:`serve_in_thread` waits for uvicorn to listen."""
GRACEFUL_SHUTDOWN_S = 5
"""uvicorn's ``timeout_graceful_shutdown``: open requests get this long on shutdown."""
UVICORN_LOOP = "auto"
"""uvloop when installed (a dependency: ~1.5× the request rate of asyncio's loop on
``GET /registration/current``), else asyncio's.  The robot links run on the same loop and use only
the portable transport API (``abort``/``close``).  httptools is used for HTTP parsing."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", type=Path, default=None, help="TOML settings file (configs/oarmreg.toml)")
    parser.add_argument("--host", default=None, help="bind address (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=None, help="TCP port (default 8750; 0 = any free port)")
    parser.add_argument("--watch", type=Path, default=None, help="folder the O-arm exports DICOM into")
    parser.add_argument("--data", type=Path, default=None, help="folder for the database and histograms")
    parser.add_argument("--robot-link", default=None, help="robot link URL, e.g. simple-message://HOST:11002")
    parser.add_argument(
        "--dicom-port", type=int, default=None, help="enable the DICOM C-STORE SCP on this port (0 = any)"
    )
    parser.add_argument(
        "--igtl-port", type=int, default=None, help="enable the OpenIGTLink server on this port (0 = any)"
    )
    parser.add_argument("--tls-cert", type=Path, default=None, help="PEM certificate: serve HTTPS")
    parser.add_argument("--tls-key", type=Path, default=None, help="PEM private key of --tls-cert")


def settings_from_args(args: argparse.Namespace) -> Any:
    from service.settings import load_settings

    return load_settings(
        args.config,
        {
            "host": args.host,
            "port": args.port,
            "watch_dir": args.watch,
            "data_dir": args.data,
            "robot.link_url": args.robot_link,
            "dicom.port": getattr(args, "dicom_port", None),
            "dicom.enabled": True if getattr(args, "dicom_port", None) is not None else None,
            "igtl.port": getattr(args, "igtl_port", None),
            "igtl.enabled": True if getattr(args, "igtl_port", None) is not None else None,
            "tls.cert_file": getattr(args, "tls_cert", None),
            "tls.key_file": getattr(args, "tls_key", None),
        },
    )


def run(args: argparse.Namespace) -> int:
    import uvicorn

    from service.http.app import create_app
    from service.http.security import forwarded_options
    from service.http.tls import uvicorn_ssl_options

    settings = settings_from_args(args)
    apply_log_settings(args, settings)
    ssl_options = uvicorn_ssl_options(settings)
    if settings.data_dir.is_dir():  # another serve on this folder: say so, not "port in use"
        from service.data_dir import hold_serve_lock

        hold_serve_lock(settings.data_dir).close()
    check_ports(settings)  # before preflight opens (and may create) the database
    raise_descriptor_limit(settings)
    preflight(settings)
    app = create_app(settings)
    limits = http_limits(settings, app)
    config = uvicorn.Config(
        app,
        host=settings.host,
        port=settings.port,
        **ssl_options,
        **limits,
        **forwarded_options(settings),
        log_config=None,  # the CLI configured logging
        timeout_graceful_shutdown=GRACEFUL_SHUTDOWN_S,
        loop=UVICORN_LOOP,
    )
    server = _Server(config, app)
    server.run()
    if not server.started:
        from registration.errors import ConfigError

        raise ConfigError(f"the service did not start on {settings.host}:{settings.port} (see the log above)")
    return 0


def http_limits(settings: Any, app: Any = None) -> dict[str, Any]:
    """uvicorn ``Config`` options bounding HTTP connections (``api.max_connections``,
    ``api.first_request_timeout_s``; :mod:`service.http.limits`)."""
    from service.http.limits import bounded_protocol

    api = settings.api
    protocol = bounded_protocol(
        api.max_connections, api.first_request_timeout_s, api.max_connections_per_address, api.write_timeout_s
    )
    if app is not None:  # the counters, for /ready and /status (service.http.health)
        app.state.http.limits = protocol.counters
    return {"http": protocol}


def raise_descriptor_limit(settings: Any) -> int:
    """Raise this process's soft ``RLIMIT_NOFILE`` to cover the configured maxima
    (:func:`service.settings.descriptor_budget`); returns the descriptors needed.

    The soft limit is only ever raised (never lowered), up to the hard limit.

    Raises
    ------
    ConfigError
        The maxima need more than the hard limit: names the largest setting and how to fix it.
    """
    import resource

    from registration.errors import ConfigError
    from service.settings import descriptor_budget

    budget = descriptor_budget(settings)
    need = sum(n for _, n in budget)
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    unlimited = resource.RLIM_INFINITY
    if hard != unlimited and need > hard:
        name, n = max(budget[:-1], key=lambda item: item[1])
        parts = ", ".join(f"{k} {v}" for k, v in budget)
        raise ConfigError(
            f"the configured connection maxima need {need} file descriptors ({parts}) but this process "
            f"may open at most {hard} (RLIMIT_NOFILE hard limit): lower '{name}' (it needs {n}) or raise "
            "the hard limit (systemd LimitNOFILE=, ulimit -Hn, /etc/security/limits.conf)"
        )
    if soft != unlimited and soft < need:
        resource.setrlimit(resource.RLIMIT_NOFILE, (need, hard))
        log.info("file descriptor limit raised from %d to %d for the connection maxima", soft, need)
    return need


def apply_log_settings(args: argparse.Namespace, settings: Any) -> None:
    """``[log] level`` / ``format`` unless ``-v`` / ``--log-level`` / ``--log-format`` said otherwise."""
    from service.cli.main import log_level_of
    from service.logsetup import configure

    level, explicit = log_level_of(args, DEFAULT_LOG_LEVEL)
    if not explicit:
        level = int(getattr(logging, settings.log.level))
    fmt = getattr(args, "log_format_sub", None) or getattr(args, "log_format", None) or settings.log.format
    configure(level, fmt)


def listeners(settings: Any) -> list[tuple[str, str, str, int]]:
    """(name, setting, host, port) of every TCP listener the settings ask for."""
    out = [("HTTP API", "port", settings.host, settings.port)]
    if settings.dicom.enabled:
        out.append(("DICOM C-STORE", "dicom.port", settings.dicom.host, settings.dicom.port))
    if settings.igtl.enabled:
        out.append(("OpenIGTLink", "igtl.port", settings.igtl.host, settings.igtl.port))
    return out


def check_ports(settings: Any) -> None:
    """Refuse to start, one line per listener, when a port is taken (before anything starts).

    A bind test (with ``SO_REUSEADDR``, as the servers use) on each configured port; ports of 0 are
    chosen by the system and always free.  Racy by nature: a port taken in between still fails at
    bind, with the server's own message.

    Raises
    ------
    ConfigError
    """
    from registration.errors import ConfigError

    lines = []
    for name, key, host, port in listeners(settings):
        if port == 0:
            continue
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        with socket.socket(family, socket.SOCK_STREAM) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind((host, port))
            except OSError as e:
                lines.append(
                    f"{name}: {host}:{port} cannot be used ({e.strerror}); another program (an oarmreg "
                    f"already running?) holds it: stop it or change '{key}'"
                )
    if lines:
        raise ConfigError("\n".join(lines))


def preflight(settings: Any) -> None:
    """Fail before uvicorn starts, with one line and the exit code, not a lifespan traceback:
    no way to authenticate, another ``serve`` on the same data folder (exit 3, naming it),
    or a database that is empty, foreign or damaged.

    Raises
    ------
    ConfigError
    """
    from service.data_dir import hold_serve_lock, make_private
    from service.store import Database

    settings.check_serving()
    make_private(settings.data_dir)
    hold_serve_lock(settings.data_dir).close()  # another serve on this folder: exit 3, naming it
    Database.open(settings.db_path).close()


class _Server:
    """uvicorn.Server that ends SSE streams before waiting for open connections on shutdown."""

    def __new__(cls, config: Any, app: Any) -> Any:
        import uvicorn

        class Server(uvicorn.Server):
            async def shutdown(self, sockets: Any = None) -> None:
                ctx = getattr(app.state, "ctx", None)
                if ctx is not None:
                    ctx.bus.close()
                await super().shutdown(sockets=sockets)

        return Server(config)


class ServerThread:
    """A running uvicorn server on a background thread (see :func:`serve_in_thread`)."""

    def __init__(
        self, server: Any, thread: threading.Thread, host: str, port: int, scheme: str = "http"
    ) -> None:
        self.server = server
        self.thread = thread
        self.host = host
        self.port = port
        self.scheme = scheme

    @property
    def base_url(self) -> str:
        return f"{self.scheme}://{self.host}:{self.port}"

    def stop(self, timeout_s: float = 30.0) -> None:
        self.server.should_exit = True
        self.thread.join(timeout_s)


def _app_http_limits(app: Any) -> dict[str, Any]:
    """:func:`http_limits` of the app's settings (an app from :func:`service.http.app.create_app`)."""
    inputs = getattr(getattr(app, "state", None), "inputs", None)
    return http_limits(inputs.settings, app) if inputs is not None else {}


def _app_forwarded_options(app: Any) -> dict[str, Any]:
    """:func:`service.http.security.forwarded_options` of the app's settings (none: not believed)."""
    from service.http.security import forwarded_options

    inputs = getattr(getattr(app, "state", None), "inputs", None)
    return forwarded_options(inputs.settings) if inputs is not None else {"proxy_headers": False}


@contextlib.contextmanager
def serve_in_thread(
    app: Any, host: str = "127.0.0.1", port: int = 0, *, ssl_options: dict[str, Any] | None = None
) -> Iterator[ServerThread]:
    """Run ``app`` with uvicorn on ``host:port`` (0 = a free port) in a background thread.

    ``ssl_options``: :func:`service.http.tls.uvicorn_ssl_options` (HTTPS; ``base_url`` says ``https``).

    The socket is bound before the thread starts, so the port is known and reserved.
    Yields once the app's lifespan has started; stops the server (lifespan shutdown
    included) and joins the thread on exit.
    """
    import uvicorn

    sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # inherited by accepted connections
    sock.bind((host, port))
    bound_port = int(sock.getsockname()[1])
    config = uvicorn.Config(
        app,
        host=host,
        port=bound_port,
        log_config=None,
        timeout_graceful_shutdown=GRACEFUL_SHUTDOWN_S,
        loop=UVICORN_LOOP,
        **(ssl_options or {}),
        **_app_http_limits(app),
        **_app_forwarded_options(app),
    )
    server = _Server(config, app)
    failure: list[BaseException] = []

    def main() -> None:
        try:
            server.run(sockets=[sock])
        except BaseException as e:  # start-up failure (lifespan error): report to the caller
            failure.append(e)

    thread = threading.Thread(target=main, name=f"uvicorn-{bound_port}", daemon=True)
    thread.start()
    started = threading.Event()
    # wait until uvicorn reports started (or the thread died), polling with a deadline
    import time

    deadline = time.monotonic() + SERVER_START_TIMEOUT_S
    while time.monotonic() < deadline:
        if server.started:
            started.set()
            break
        if not thread.is_alive():
            break
        thread.join(0.02)
    if not started.is_set():
        server.should_exit = True
        thread.join(10.0)
        sock.close()
        if failure:
            raise failure[0]
        raise RuntimeError(f"uvicorn did not start on {host}:{bound_port} within {SERVER_START_TIMEOUT_S} s")
    handle = ServerThread(server, thread, host, bound_port, "https" if ssl_options else "http")
    try:
        yield handle
    finally:
        handle.stop()
        sock.close()
