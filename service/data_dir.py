"""The data folder belongs to one ``serve`` and to the service's user alone.

* :func:`hold_serve_lock`: an exclusive ``flock`` on ``<data>/serve.lock``, held while the service
  runs, whose text names the holder; a second ``serve`` on the same folder refuses to start
  (:class:`ServeLockError`, a configuration error: exit 3).  This is a lock of its own: the shared
  lock on ``<db>.lock`` that ``oarmreg restore`` checks (:mod:`service.store.integrity`) keeps its
  meaning.
* :func:`make_private`: the process umask :data:`UMASK` (every file the service creates is 0600,
  every folder 0700) and the folder itself (and whatever an older version left in it) brought to
  those modes.  The database, its WAL, the intake files and the audit log hold patient data.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import socket
import stat
from datetime import UTC, datetime
from pathlib import Path
from typing import IO

from service.errors import ServeLockError

log = logging.getLogger(__name__)

SERVE_LOCK_NAME = "serve.lock"
UMASK = 0o077
"""Files 0600, folders 0700: only the service's user reads patient data."""
FILE_MODE = 0o600
DIR_MODE = 0o700


def serve_lock_path(data_dir: Path) -> Path:
    return data_dir / SERVE_LOCK_NAME


def hold_serve_lock(data_dir: Path) -> IO[bytes]:
    """Take ``<data_dir>/serve.lock`` exclusively (kept until the returned file is closed) and write
    who holds it.

    Raises
    ------
    ServeLockError
        Another process holds it; the message names it (pid, host, start time).
    """
    path = serve_lock_path(data_dir)
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, FILE_MODE)
    f = os.fdopen(fd, "r+b")
    try:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = f.read(200).decode("utf-8", "replace").strip() or "a process that wrote nothing yet"
        f.close()
        raise ServeLockError(
            f"another oarmreg serve is running on the data folder {data_dir} ({holder}; it holds {path}); "
            "stop it first, or give this one another data folder (--data)"
        ) from None
    f.seek(0)
    f.truncate()
    f.write(f"pid {os.getpid()} on {socket.gethostname()}, since {datetime.now(UTC).isoformat()}\n".encode())
    f.flush()
    return f


def make_private(data_dir: Path) -> None:
    """Set the umask, create ``data_dir`` 0700 and bring what is in it to 0700 / 0600 (symlinks and
    other special files are left alone)."""
    os.umask(UMASK)
    data_dir.mkdir(parents=True, exist_ok=True, mode=DIR_MODE)
    _chmod(data_dir, DIR_MODE)
    for root, dirs, files in os.walk(data_dir):
        for name in dirs:
            _chmod(Path(root) / name, DIR_MODE)
        for name in files:
            _chmod(Path(root) / name, FILE_MODE)


def _chmod(path: Path, mode: int) -> None:
    with contextlib.suppress(OSError):
        st = path.lstat()
        if (stat.S_ISDIR(st.st_mode) or stat.S_ISREG(st.st_mode)) and stat.S_IMODE(st.st_mode) != mode:
            os.chmod(path, mode)
            log.debug("data folder: %s was %o, now %o", path, stat.S_IMODE(st.st_mode), mode)
