"""``oarmreg detect`` imports only what detection needs (issue #11: whole-process detect time).

Checked in a fresh interpreter on ``sys.modules`` after the command ran (not by timing): the
service's web, DICOM-network, robot-model and plotting stacks, ``scipy.optimize`` (the ``model``
method's optimiser, ~0.3 s to import) and ``scipy.ndimage`` (0.3–1 s; only the split of an
oversized blob imports it, on demand) stay out of the default detect path.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers.scan_cache import simulated_scan

ROOT = Path(__file__).resolve().parents[4]

NOT_FOR_DETECT = (
    "fastapi",
    "uvicorn",
    "pydantic",
    "pydantic_settings",
    "starlette",
    "pynetdicom",
    "pinocchio",
    "matplotlib",
    "httpx",
    "watchdog",
    "service.http.app",
    "service.registrations.orchestrator",
    "service.settings",
    "scipy.optimize",
    "scipy.ndimage",
    "mocks",
)
"""Modules (or packages) a default ``oarmreg detect`` must not import."""

PROBE = """
import contextlib, io, json, sys
from service.cli.main import main
with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
    code = main(["detect", sys.argv[1]])
print(json.dumps({"code": code, "modules": sorted(sys.modules)}))
"""


@pytest.fixture(scope="module")
def small_series(tmp_path_factory: pytest.TempPathFactory, phantom) -> Path:  # type: ignore[no-untyped-def]
    """A real simulated series of the built-in (steel) phantom: detect runs its whole path."""
    from mocks.oarm.dicom_export import write_dicom_series
    from mocks.oarm.simulator import AcquisitionSettings, demo_pose

    out = tmp_path_factory.mktemp("detect-imports") / "series"
    write_dicom_series(simulated_scan(phantom, demo_pose(), AcquisitionSettings.preset("small")), out)
    return out


def test_detect_does_not_import_the_service_stack(small_series: Path) -> None:
    out = subprocess.run(
        [sys.executable, "-c", PROBE, str(small_series)], cwd=ROOT, capture_output=True, text=True, check=True
    )
    doc = json.loads(out.stdout)
    modules = set(doc["modules"])
    assert doc["code"] == 0
    # the probe ran the whole detect path: loader, detection and the steel estimator, found by name
    assert {
        "registration.detection",
        "registration.dicom.loader",
        "registration.detection.estimators.rays",
        "registration.detection.estimators.ray_fit",
    } <= modules
    # the other estimators' modules are not imported: each is looked up only when a detection names it
    others = {f"registration.detection.estimators.{m}" for m in ("subvoxel", "model", "paper", "core")}
    assert modules.isdisjoint(others | {"registration.detection.estimators.sphere_fit"})
    loaded = sorted(m for m in modules if any(m == n or m.startswith(n + ".") for n in NOT_FOR_DETECT))
    assert loaded == []
