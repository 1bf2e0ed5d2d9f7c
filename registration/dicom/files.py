"""Which paths the loader may open: regular files only, inside the folder it was pointed at.

A named pipe (FIFO) blocks ``open()`` until a writer appears and a device file can block or have
side effects on ``read()``; neither is ever opened.  Every candidate is checked with ``os.stat`` before
``open`` (so a FIFO or device is refused without being opened), opened with ``O_NONBLOCK`` and checked
again with ``os.fstat`` on the open descriptor (so a file swapped for a FIFO between the two calls is
still refused).  Symbolic links are followed only to a regular file inside the folder tree the loader
was pointed at; a loop (``ELOOP``) or a target outside is refused, as is a DICOMDIR reference that
leaves the file-set's folder.
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path
from typing import BinaryIO, Final

from registration.dicom.errors import NotRegularFileError

MAX_FILE_BYTES: Final = 4 * 1024**3
"""Largest single file the loader opens (bytes).  A 512 x 512 x 192 O-arm volume as one Enhanced CT
file is 96 MiB; 4 GiB is the largest 32-bit Pixel Data length (PS3.5 §7.1.2) plus its header."""

_KINDS: Final = (
    (stat.S_ISFIFO, "a named pipe (FIFO)"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISDIR, "a folder"),
)


def kind_of(mode: int) -> str:
    """What a non-regular ``st_mode`` is, for a message."""
    return next((name for test, name in _KINDS if test(mode)), f"not a regular file (mode {mode:o})")


def regular_file_problem(path: Path, inside: Path | None = None) -> str:
    """``""`` when ``path`` may be opened, else why not (one sentence, without the path).

    ``inside``: the folder a symbolic link (or DICOMDIR reference) must resolve into.
    """
    try:
        lst = os.lstat(path)
    except OSError as exc:
        return f"cannot stat ({type(exc).__name__}: {exc.strerror})"
    is_link = stat.S_ISLNK(lst.st_mode)
    try:
        st = os.stat(path) if is_link else lst
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            return "symbolic link loop (ELOOP): never followed; remove the link"
        return f"dangling symbolic link ({exc.strerror}); remove the link"
    if not stat.S_ISREG(st.st_mode):
        return f"{kind_of(st.st_mode)}, not a regular file: never opened; remove it from the folder"
    if st.st_size > MAX_FILE_BYTES:
        return f"{st.st_size} bytes, more than the {MAX_FILE_BYTES} a DICOM image file can hold"
    if inside is not None and not is_inside(path, inside):
        return f"resolves outside {inside} (to {os.path.realpath(path)}); copy the file into the folder"
    return ""


def is_inside(path: Path, folder: Path) -> bool:
    """True when ``path`` (links resolved) lies in ``folder`` (links resolved)."""
    real, base = os.path.realpath(path), os.path.realpath(folder)
    return real == base or real.startswith(base.rstrip(os.sep) + os.sep)


def open_regular(path: Path) -> BinaryIO:
    """Open ``path`` for binary reading only if it is a regular file (``stat`` before, ``fstat`` after).

    Raises
    ------
    NotRegularFileError
        A FIFO, device, socket or folder (never opened), or a file replaced by one meanwhile.
    OSError
        The file cannot be opened.
    """
    problem = regular_file_problem(path)
    if problem:
        raise NotRegularFileError(f"{path}: {problem}", files=[path])
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise NotRegularFileError(f"{path}: {kind_of(st.st_mode)}, not a regular file", files=[path])
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise
