"""``oarmreg mock robot`` as its own process: serves, then stops cleanly on SIGINT and SIGTERM."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
from pathlib import Path
from urllib.parse import urlsplit

import pytest

from drivers.simple_message import FrameReassembler, JointPosition, decode_message

REPO_ROOT = Path(__file__).resolve().parents[2]
DEADLINE_S = 20.0


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_mock_controller_streams_then_stops_on_a_signal(sig: signal.Signals) -> None:
    """A client gets simple_message frames; the signal (sent while the client is connected) ends
    the process with exit code 0 and nothing on stderr but the log."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "mock", "robot", "--link", "simple-message://127.0.0.1:0"],
        cwd=REPO_ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        url = urlsplit(proc.stdout.readline().strip())
        assert url.scheme == "simple-message"
        with socket.create_connection((url.hostname, url.port), timeout=DEADLINE_S) as sock:
            frames: list[bytes] = []
            reassembler = FrameReassembler()
            while len(frames) < 3:
                frames += reassembler.feed(sock.recv(4096))
            assert any(isinstance(decode_message(f), JointPosition) for f in frames)  # real frames
            proc.send_signal(sig)
            _, err = proc.communicate(timeout=DEADLINE_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    assert "Traceback" not in err
