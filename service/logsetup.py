"""Logging set-up for the ``oarmreg`` command line: text or one JSON object per line.

The library parts never configure logging; :func:`service.cli.main.main` calls :func:`configure` once,
and ``oarmreg serve`` may lower or raise the level to the ``[log] level`` setting.
"""

from __future__ import annotations

import json
import logging
import re
import sys
from datetime import UTC, datetime
from typing import Literal
from urllib.parse import unquote_plus

LogFormat = Literal["text", "json"]
LOG_FORMATS: tuple[LogFormat, ...] = ("text", "json")
LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")
TEXT_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


class JsonFormatter(logging.Formatter):
    """One JSON object per record: ``ts`` (UTC ISO 8601), ``level``, ``logger``, ``message``,
    and ``exc`` (the formatted traceback) when there is one; for journald / log shippers."""

    def format(self, record: logging.LogRecord) -> str:
        doc: dict[str, object] = {
            "ts": datetime.fromtimestamp(record.created, UTC).isoformat(timespec="milliseconds"),
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
        }
        if record.exc_info:
            doc["exc"] = self.formatException(record.exc_info)
        return json.dumps(doc, ensure_ascii=False)


SECRET_QUERY_PARAMS = ("ticket",)
"""Query parameters whose values never reach a log: the single-use ``GET /events?ticket=`` (a
bearer credential while it lives; :mod:`service.http.tickets`)."""
_QUERY_PAIR = re.compile(r"([?&])([^=&#\s]*)=([^&#\s]*)")
REDACTED = "<redacted>"
ACCESS_LOGGER = "uvicorn.access"


def redact_query(text: str) -> str:
    """``text`` with the value of every :data:`SECRET_QUERY_PARAMS` parameter replaced by ``<redacted>``;
    a parameter's name is compared after URL decoding (``%74icket`` is ``ticket``), as the gate reads it."""

    def _pair(m: re.Match[str]) -> str:
        if unquote_plus(m.group(2)) in SECRET_QUERY_PARAMS:
            return f"{m.group(1)}{m.group(2)}={REDACTED}"
        return m.group(0)

    return _QUERY_PAIR.sub(_pair, text)


class RedactSecretsFilter(logging.Filter):
    """Redacts secret query parameters in a record's message and arguments (uvicorn's access log
    passes the request's path with its query string as an argument)."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.msg, str):
            record.msg = redact_query(record.msg)
        if isinstance(record.args, tuple):
            record.args = tuple(redact_query(a) if isinstance(a, str) else a for a in record.args)
        return True


def install_redaction() -> None:
    """Put :class:`RedactSecretsFilter` on uvicorn's access logger, once (idempotent): a logger's
    filters run before any handler, whoever configured the handlers."""
    logger = logging.getLogger(ACCESS_LOGGER)
    if not any(isinstance(f, RedactSecretsFilter) for f in logger.filters):
        logger.addFilter(RedactSecretsFilter())


PER_INSTANCE_MESSAGES = ("Received Store Request", "Sending Store Request", "Received Store Response")
"""pynetdicom's INFO lines written once per DICOM instance (132 a scan): DEBUG here."""
PYNETDICOM_HANDLERS = "pynetdicom._handlers"


class PerInstanceToDebugFilter(logging.Filter):
    """Turns pynetdicom's per-instance INFO lines (:data:`PER_INSTANCE_MESSAGES`) into DEBUG records,
    dropped unless the ``pynetdicom`` logger is at DEBUG; its association lines stay at INFO."""

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno != logging.INFO or not str(record.msg).startswith(PER_INSTANCE_MESSAGES):
            return True
        record.levelno, record.levelname = logging.DEBUG, "DEBUG"
        return logging.getLogger(PYNETDICOM_HANDLERS).getEffectiveLevel() <= logging.DEBUG


def install_per_instance_demotion() -> None:
    """Put :class:`PerInstanceToDebugFilter` on pynetdicom's handler logger, once (idempotent)."""
    logger = logging.getLogger(PYNETDICOM_HANDLERS)
    if not any(isinstance(f, PerInstanceToDebugFilter) for f in logger.filters):
        logger.addFilter(PerInstanceToDebugFilter())


def configure(level: int, fmt: LogFormat = "text") -> None:
    """Send every record at ``level`` and above to stderr as text or JSON (replaces earlier handlers)."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonFormatter() if fmt == "json" else logging.Formatter(TEXT_FORMAT))
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    root.addHandler(handler)
    root.setLevel(level)
    install_redaction()
    install_per_instance_demotion()


def set_level(level: int) -> None:
    logging.getLogger().setLevel(level)
