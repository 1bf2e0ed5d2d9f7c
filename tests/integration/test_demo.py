"""``oarmreg demo``, the README's first command, run as a user runs it, archiving to a real PACS.

One run (≈ 12 s on 2 cores): the mock controller, the O-arm simulator, C-STORE into the service,
``/register``, the OpenIGTLink check, the archive of the registration's Spatial Registration
object to Orthanc (``--pacs``), the moved-O-arm verification.  Orthanc's REST API says where the
object landed.  Without ``--pacs`` the demo runs the same code with the archive step skipped.

The one change from the README's ``make demo``: ``--preset small`` (a 160 x 160 x 96 scan, 180
views) instead of the default ``demo`` preset (512 x 512 x 132, 240 views), as the calibration
walkthrough test runs its doc with a smaller scan.  Every step above is the same code at either
size; the three ``demo``-preset simulations were 20 of this test's 31 s of CPU, about 4 % of the
whole suite's (issue #42 item 8: CI under load).  What the default size adds is covered where it
is cheaper: the verification pose's margin inside the ``demo`` preset's volume
(tests/integration/test_demo_verification_pose.py) and detection at its 0.415 mm pixels
(tests/accuracy/test_end_to_end.py, tests/integration/test_cli_detect.py).
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.integration.orthanc import AE_TITLE as ORTHANC_AET
from tests.integration.orthanc import ORTHANC, running_orthanc

DEMO_TIMEOUT_S = 300.0
"""Generous: ≈ 12 s idle; a loaded CI machine takes about three times that."""

pytestmark = pytest.mark.skipif(ORTHANC is None, reason="Orthanc not installed (.ci/run installs it)")


def oarmreg(*args: str, timeout_s: float = DEMO_TIMEOUT_S) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "service.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        check=False,
    )


@pytest.mark.slow
def test_demo_registers_verifies_and_archives_to_a_pacs(tmp_path: Path) -> None:
    with running_orthanc(tmp_path / "orthanc") as orthanc:
        orthanc.add_modality("oarmreg-demo", "OARMREG", 1)  # the demo's calling AE title (the default)
        out = tmp_path / "demo"
        run = oarmreg(
            "demo", "--preset", "small", "--out", str(out),
            "--pacs", f"{ORTHANC_AET}@127.0.0.1:{orthanc.dicom_port}",
        )  # fmt: skip
        assert run.returncode == 0, run.stderr[-3000:]
        text = run.stdout

        assert re.search(r"== Registration 1 \(accepted", text), text
        matched = re.search(r"spheres expected / detected / matched : (\d+) / (\d+) / (\d+)", text)
        assert matched is not None and int(matched[3]) >= 26, text

        igtl = re.search(r"max \|IGTL − diag\(-1,-1,1,1\)·REST\| = (\S+)", text)
        assert igtl is not None and float(igtl[1]) < 1e-4, text  # float32 on the wire, mm-sized entries

        sent = re.search(r"sent after \d+ attempt\(s\), C-STORE status 0x0000", text)
        assert sent is not None, text
        uid = re.search(r"SOP Instance UID (\S+)", text)
        assert uid is not None
        instance = orthanc.find_instance(uid[1])
        assert instance is not None, f"Orthanc holds no instance {uid[1]}"
        tags = orthanc.get(f"/instances/{instance}/simplified-tags")
        assert tags["Modality"] == "REG"
        assert tags["SOPClassUID"] == "1.2.840.10008.5.1.4.1.1.66.1"  # Spatial Registration Storage

        verdict = re.search(r"matched (\d+)/(\d+): mean \S+ mm, RMS \S+ mm, max \S+ mm → (PASS|FAIL)", text)
        assert verdict is not None, text
        assert verdict[3] == "PASS", text
        assert int(verdict[1]) == int(verdict[2]), text  # every sphere in view at the chain-moving pose
        assert "does not bound the error elsewhere" in text
        assert (out / "verification-histogram.png").is_file()


@pytest.mark.parametrize("spec", ["ORTHANC@127.0.0.1:", "127.0.0.1:4242", "A@host:99999999"])
def test_demo_refuses_a_malformed_pacs_before_starting_anything(spec: str) -> None:
    run = oarmreg("demo", "--pacs", spec, timeout_s=60.0)
    assert run.returncode == 3, (run.returncode, run.stderr)
    assert "expected AE@HOST:PORT" in run.stderr
    assert "Traceback" not in run.stderr
