"""Issue 19 item 7 (b): a still robot must not be refused while big C-STORE instances are decoded.

Against the real service as the OR PC runs it (``oarmreg serve``, a subprocess; the robot link read in
its child process, the default), the robot still and streaming (``oarmreg mock robot``, 50 Hz
simple_message, a process of its own), at the default ``stillness.max_gap_s`` (0.25 s):

1. a big CT instance (``SIZE_PX`` x ``SIZE_PX`` int16, 763 MiB: within ``dicom.max_instance_mb``,
   about a 1500-frame 512 x 512 Enhanced CT) arrives by C-STORE (dcmtk ``storescu``), and the
   service receives, checks, hashes and decodes it;
2. then an ordinary simulated O-arm scan arrives (96 slices); its stillness window (``WINDOW_S``
   before its first slice until its last) covers the big instance's reception and decoding;
3. the scan must be ``complete`` and judged still, ``POST /register`` must register it, and every
   ``/status`` sampled meanwhile must show the link ``connected`` and the service healthy.

Before the fix the link was read on a thread of the service process, and pynetdicom / pydicom copy a
received instance whole while holding the GIL (the dataset parsed from its ``BytesIO``, then
``encoded_dataset()`` twice): the reader could not run, the receive clock showed gaps over
``max_gap_s`` and the still robot's scan was refused as "Robot moved during the scan", while the
link's 0.06 s stale threshold flapped ``stale`` / ``connected``.  On the 2-core reference machine one
such copy of a 288 MB instance (the issue's 12000 x 12000) held the GIL for 0.16-0.18 s, so a
refusal needed two copies back to back: two 288 MB instances at once failed this test in 2 of 3
runs, two 512 MB instances at once in 9 of 9 (5 refused, 4 only seen ``stale``), one 512 MB
instance in 12 of 12 (11 refused, gaps of 0.27-0.58 s, most under 0.31 s), one instance of
``SIZE_PX`` in 10 of 10, refused with gaps of 0.38-0.44 s: the margin over 0.25 s chosen here.

Every wait polls with a deadline; nothing sleeps.  The big files are sparse (their pixel data is a
hole of zeros), written in milliseconds.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import pytest

from service.intake.cstore_intake import INTAKE_FOLDER
from tests.faults._service import (
    DEADLINE_S,
    TOKEN,
    free_port,
    mock_controller_process,
    served,
    wait_for,
    write_config,
)
from tests.helpers.scan_cache import simulated_scan
from tests.helpers.system_tools import system_tool

STORESCU = system_tool("storescu")
pytestmark = pytest.mark.skipif(STORESCU is None, reason="dcmtk storescu not installed (.ci/run installs it)")

AE_TITLE = "OARMREG"
SIZE_PX = 20000
"""Rows = Columns of the big instance (int16: 800 MB of pixel data)."""
N_BIG = 1
"""Big instances, each its own series over its own association, sent at once."""
WINDOW_S = 6.0
"""``stillness.window_s`` here (60 s by default): the scan's window reaches back over the big
instance's reception and decoding, which end just before the scan is sent (the old code's gaps fell
3.3-4.0 s before the scan's first slice)."""


@dataclass(frozen=True)
class Outbox:
    big: list[Path]
    """One folder per big instance."""
    scan: Path
    scan_uid: str


def _big_instance(folder: Path, size_px: int) -> Path:
    """A CT Image Storage Part-10 file of ``size_px`` x ``size_px`` int16 zeros, its own series.

    The header is pydicom's; the pixel data element is appended by hand with its length and the file
    extended to it (a hole reads as zeros), so its 800 MB cost no time or memory to write."""
    import numpy as np
    from pydicom.uid import generate_uid

    from tests.helpers.dicom_factory import ct_dataset

    folder.mkdir(parents=True)
    ds = ct_dataset(
        np.zeros((1, 1), np.int16), position_mm=(0.0, 0.0, 0.0), series_uid=generate_uid(),
        frame_of_reference_uid=generate_uid(), study_uid=generate_uid(),
    )  # fmt: skip
    ds.Rows = ds.Columns = size_px
    del ds.PixelData
    path = folder / "big.dcm"
    ds.save_as(path, enforce_file_format=True)
    n_bytes = size_px * size_px * 2
    with path.open("r+b") as f:
        f.seek(0, os.SEEK_END)
        # (7FE0,0010) OW, Explicit VR Little Endian: tag, VR, 2 reserved bytes, 4-byte length
        f.write(b"\xe0\x7f\x10\x00OW\x00\x00" + n_bytes.to_bytes(4, "little"))
        f.truncate(f.tell() + n_bytes)
    return path


def _outbox(root: Path, phantom: Any) -> Outbox:
    """The big instances and the scan, written while the service's joint history fills."""
    from mocks.oarm.dicom_export import write_dicom_series
    from mocks.oarm.simulator import AcquisitionSettings
    from registration.model.frames import transform_from_xyz_rpy

    big = [_big_instance(root / f"big{k}", SIZE_PX).parent for k in range(N_BIG)]
    image_from_phantom = transform_from_xyz_rpy([2.0, -3.0, 1.0], [10.0, -6.0, 20.0])
    scan = simulated_scan(phantom, image_from_phantom, AcquisitionSettings.preset("small"))
    res = write_dicom_series(scan, root / "scan", write_truth=False)
    return Outbox(big, root / "scan", str(res.series_uid))


def _storescu(folder: Path, port: int, calling_ae: str) -> subprocess.Popen[bytes]:
    """``storescu`` sending every file of ``folder`` over one association; its output to ``folder``.log."""
    assert STORESCU is not None
    with folder.with_suffix(".log").open("wb") as out:
        return subprocess.Popen(
            [STORESCU, "-aet", calling_ae, "-aec", AE_TITLE, "+sd", "127.0.0.1", str(port), str(folder)],
            stdout=out,
            stderr=subprocess.STDOUT,
            # dcmtk disables Nagle's algorithm on TCP_NODELAY=1; otherwise each C-STORE of the 96 slices
            # waits for the SCP's delayed ACK (~40 ms)
            env={**os.environ, "TCP_NODELAY": "1"},
        )


@dataclass
class LinkWatch:
    """``/status`` sampled while SCUs run: the link's state, the service's health, the largest receive
    gap the link reports (where it does)."""

    client: httpx.Client
    states: list[str] = field(default_factory=list)
    unhealthy: list[list[str]] = field(default_factory=list)
    receive_gaps_s: list[float] = field(default_factory=list)

    def until_done(self, procs: list[subprocess.Popen[bytes]], what: str) -> None:
        def sample() -> bool:
            st = self.client.get("/status").json()
            self.states.append(st["link"]["state"])
            if not st["healthy"]:
                self.unhealthy.append(list(st["problems"]))
            gap_s = st["link"].get("max_receive_gap_s")
            if gap_s is not None:
                self.receive_gaps_s.append(float(gap_s))
            return all(p.poll() is not None for p in procs)

        wait_for(sample, what, DEADLINE_S * 3)
        failed = [
            (p.returncode, Path(p.args[-1]).with_suffix(".log").read_text(errors="replace")[-800:])
            for p in procs
            if p.returncode != 0
        ]
        if failed:  # say why the service refused (0xA700 with a full disk, say), not only storescu's code
            dicom = self.client.get("/status").json()["listeners"]["dicom"]
            raise AssertionError(f"{failed}; the service's DICOM listener: {dicom}; problems seen: "
                                 f"{self.unhealthy[-3:]}")  # fmt: skip

    def summary(self) -> str:
        n = {s: self.states.count(s) for s in sorted(set(self.states))}
        gap = f"{max(self.receive_gaps_s):.3f} s" if self.receive_gaps_s else "not reported"
        return f"link states sampled {n}, largest receive gap {gap}"


@pytest.fixture
def service(tmp_path: Path) -> Iterator[tuple[httpx.Client, int]]:
    with mock_controller_process() as url:
        cfg, port, dicom_port = tmp_path / "oarmreg.toml", free_port(), free_port()
        write_config(cfg, {
            "watch_dir": str(tmp_path / "watch"), "data_dir": str(tmp_path / "data"), "api_token": TOKEN,
            "port": port, "robot.link_url": url, "robot.connect_timeout_s": 2.0,
            "stillness.window_s": WINDOW_S,
            "dicom.enabled": True, "dicom.port": dicom_port, "dicom.ae_title": AE_TITLE,
        })  # fmt: skip
        try:
            with served(cfg, port) as (_serve, client):
                yield client, dicom_port
        finally:
            # the received copy of the big instance is 800 MB of real disk (pytest keeps 3 runs' tmp)
            shutil.rmtree(tmp_path / "data" / INTAKE_FOLDER, ignore_errors=True)


def test_a_still_robot_is_still_while_a_big_instance_is_decoded(
    service: tuple[httpx.Client, int], phantom: Any, tmp_path: Path
) -> None:
    c, dicom_port = service
    need_b = 3 * SIZE_PX * SIZE_PX * 2  # pynetdicom's received temp file + the intake's copy, + margin
    free_b = shutil.disk_usage(tmp_path).free
    assert free_b > need_b, (
        f"{free_b / 1e9:.1f} GB free under {tmp_path}; this test receives an 800 MB instance twice over "
        f"and needs {need_b / 1e9:.1f} GB: free disk space (old pytest tmp folders, say) and run it again"
    )
    outbox = _outbox(tmp_path / "outbox", phantom)
    wait_for(lambda: c.get("/status").json()["link"]["state"] == "connected", "the robot link to connect")
    before = c.get("/status").json()["listeners"]["dicom"]["counters"]
    watch = LinkWatch(c)
    watch.until_done(
        [_storescu(folder, dicom_port, f"BIG{k}") for k, folder in enumerate(outbox.big)],
        "the big instance(s) stored",
    )

    def watched() -> bool:  # as a rule it is by now: the link connected before the big instance came
        link = c.get("/status").json()["link"]
        return bool(link["state"] == "connected" and link["history_s"] > WINDOW_S + 0.5)

    wait_for(watched, "the joint history to cover a window before the scan")
    watch.until_done([_storescu(outbox.scan, dicom_port, "OARM")], "the scan sent")

    def recorded() -> dict[str, Any] | None:
        mine = [s for s in c.get("/scans").json() if s["series_uid"] == outbox.scan_uid]
        return next((s for s in mine if s["status"] != "receiving"), None)

    scan = wait_for(recorded, "the scan recorded")
    counters = c.get("/status").json()["listeners"]["dicom"]["counters"]
    # the load happened: the big instance(s) received whole, not refused
    assert counters["bytes"] - before["bytes"] >= N_BIG * SIZE_PX * SIZE_PX * 2, (before, counters)
    assert scan["status"] == "complete", scan
    j = scan["joints"]
    assert j["still"] is True and j["stillness_reason"] == "", (j["stillness_reason"], watch.summary(), j)
    r = c.post("/register", json={"scan_id": scan["id"]})
    assert r.status_code == 200, (r.text, watch.summary())
    assert r.json()["scan_id"] == scan["id"], r.json()
    # the link never looked stale (it flapped at the 0.06 s threshold before) and the service stayed healthy
    assert set(watch.states) == {"connected"}, watch.summary()
    assert watch.unhealthy == [], watch.unhealthy
