"""``oarmreg send DIR --to AE@HOST:PORT`` pushes a series to the service's own Storage SCP over
loopback (issue 42, item 3); pynetdicom's per-instance lines are DEBUG, not INFO."""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from service.cli.main import main
from service.intake.storage_scp import ScpCallbacks, StorageScp
from service.settings import DicomSettings
from tests.helpers.dicom_factory import ramp_volume, write_series

DEADLINE_S = 10.0
N_SLICES = 4


@pytest.fixture
def scp(tmp_path: Path) -> Iterator[tuple[int, list[int], threading.Event]]:
    counts: list[int] = []
    released = threading.Event()

    def on_release(_d: Path, n: int, _ae: str) -> None:
        counts.append(n)
        released.set()

    server = StorageScp(
        DicomSettings(port=0), tmp_path / "intake", ScpCallbacks(on_release, lambda *_: None, lambda *_: None)
    )
    server.start()
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    try:
        yield server.port, counts, released
    finally:
        server.stop()
        root.handlers[:] = handlers
        root.setLevel(level)


@pytest.fixture
def series(tmp_path: Path) -> Path:
    folder = tmp_path / "export" / "series1"
    folder.mkdir(parents=True)
    write_series(folder, ramp_volume(N_SLICES))
    (tmp_path / "export" / "README.txt").write_text("not DICOM")
    return tmp_path / "export"


@pytest.mark.parametrize("level", ["INFO", "DEBUG"])
def test_send_stores_the_series_and_logs_instances_at_debug_only(
    level: str,
    scp: tuple[int, list[int], threading.Event],
    series: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    port, counts, released = scp
    code = main(["send", str(series), "--to", f"OARMREG@127.0.0.1:{port}", "--log-level", level])
    assert code == 0
    assert released.wait(DEADLINE_S) and counts == [N_SLICES]
    out, err = capsys.readouterr()
    assert f"sent {N_SLICES} instance(s) to OARMREG@127.0.0.1:{port}" in out
    assert "1 non-DICOM file(s) skipped" in out
    per_instance = [ln for ln in err.splitlines() if "Store Request" in ln]
    if level == "INFO":
        assert per_instance == [], err[-2000:]
    else:
        assert len([ln for ln in per_instance if "Received Store Request" in ln]) == N_SLICES
        assert all(" DEBUG " in ln for ln in per_instance)


def test_send_refuses_a_malformed_address_naming_the_form(
    series: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as e:
        main(["send", str(series), "--to", "OARMREG@127.0.0.1:70000"])
    assert e.value.code == 2
    assert "expected AE@HOST:PORT" in capsys.readouterr().err


def test_send_help_is_whole(capsys: pytest.CaptureFixture[str]) -> None:
    """The mock's own entry point: its --help description ends with a full stop, not mid-sentence."""
    from mocks.oarm.cstore import main as cstore_main

    with pytest.raises(SystemExit):
        cstore_main(["--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert "over one association released at the end." in help_text
