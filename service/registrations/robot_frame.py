"""The robot base frame's DICOM Frame of Reference UID, minted once per data folder.

The Spatial Registration object (``registration/io/sro.py``) names the robot frame by a UID;
it must stay the same for every registration of an installation, so it is stored in
``<data_dir>/robot_frame_of_reference_uid.txt``.  Minting is atomic and race-free: the UID
is written to a temp file (fsync) and hard-linked into place, so two processes starting at
once agree on one UID.
"""

from __future__ import annotations

import contextlib
import logging
import os
import uuid
from pathlib import Path

from pydicom.uid import generate_uid

from registration.dicom.uids import is_dicom_uid
from service.errors import RobotFrameUidError

log = logging.getLogger(__name__)

FILE_NAME = "robot_frame_of_reference_uid.txt"


def _read(path: Path) -> str:
    uid = path.read_text(encoding="ascii").strip()
    if not is_dicom_uid(uid):
        raise RobotFrameUidError(
            f"{path} holds {uid[:80]!r}, not a DICOM UID; restore it from a backup (registrations "
            "already archived name the old UID) or delete it to mint a new one"
        )
    return uid


def robot_frame_uid(data_dir: Path) -> str:
    """The robot base frame's Frame of Reference UID for ``data_dir`` (minted on first call)."""
    data_dir.mkdir(parents=True, exist_ok=True)
    path = data_dir / FILE_NAME
    if path.exists():
        return _read(path)
    uid = generate_uid()
    tmp = data_dir / f".{FILE_NAME}.{uuid.uuid4().hex}.part"
    with open(tmp, "w", encoding="ascii") as f:
        f.write(uid + "\n")
        f.flush()
        os.fsync(f.fileno())
    try:
        os.link(tmp, path)  # fails if another process got there first
    except FileExistsError:
        return _read(path)
    finally:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
    fd = os.open(data_dir, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
    log.info("minted robot frame of reference UID %s in %s", uid, path)
    return uid
