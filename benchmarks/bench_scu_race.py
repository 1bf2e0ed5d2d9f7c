"""pynetdicom's SCU reactor race: responses lost with and without :mod:`dicomnet.scu`.

A pynetdicom SCP answers C-ECHOs on loopback. A pynetdicom SCU sends ``--n`` of them, 200 per
association, while ``--busy`` processes spin on the CPU, first through plain ``AE.associate`` and
then through :func:`dicomnet.scu.associate`. Every request that comes back without a status
counts as lost: the reactor took its response, or the association was already aborted after such a
loss. Python's thread switch interval is set to 1 µs so the race window comes up often. The
counts depend on the machine and its load. Run it again when pynetdicom is upgraded: a plain count
of 0 over several runs would mean upstream fixed it.

Run: ``.venv/bin/python -m benchmarks.bench_scu_race [--n 20000] [--busy 3]``
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import sys
import time
from collections.abc import Callable
from typing import Any

PER_ASSOCIATION = 200
VERIFICATION = "1.2.840.10008.1.1"
"""Verification SOP Class (C-ECHO), PS3.4 Annex A."""


def _spin() -> None:
    while True:
        pass


def lost_echoes(n: int, connect: Callable[[Any, str, int], Any]) -> tuple[int, float]:
    """Send ``n`` C-ECHOs, 200 per association; return (lost, seconds)."""
    from pynetdicom import AE

    scp = AE()
    scp.add_supported_context(VERIFICATION)
    server = scp.start_server(("127.0.0.1", 0), block=False)
    assert server is not None  # block=False returns the running server
    port = int(server.server_address[1])
    ae = AE()
    ae.add_requested_context(VERIFICATION)
    ae.dimse_timeout = 2.0  # a lost response costs this long
    lost, t0 = 0, time.perf_counter()
    try:
        for _ in range(n // PER_ASSOCIATION):
            assoc = connect(ae, "127.0.0.1", port)
            for i in range(PER_ASSOCIATION):
                if not assoc.is_established:  # aborted after a loss: the rest count as lost
                    lost += PER_ASSOCIATION - i
                    break
                if "Status" not in assoc.send_c_echo():
                    lost += 1
            if assoc.is_established:
                assoc.release()
    finally:
        server.shutdown()
    return lost, time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    p.add_argument("--n", type=int, default=20000, help="C-ECHOs per variant")
    p.add_argument("--busy", type=int, default=3, help="CPU-spinning processes beside the SCU")
    a = p.parse_args(argv)
    from dicomnet.scu import associate

    sys.setswitchinterval(1e-6)
    spinners = [mp.Process(target=_spin, daemon=True) for _ in range(a.busy)]
    for s in spinners:
        s.start()
    try:
        rows = [
            ("plain AE.associate", lost_echoes(a.n, lambda ae, h, port: ae.associate(h, port))),
            ("dicomnet.scu.associate", lost_echoes(a.n, associate)),
        ]
    finally:
        for s in spinners:
            s.terminate()
    print(f"{a.n} C-ECHOs per variant, {a.busy} busy processes, switch interval 1 µs")
    print(f"{'variant':<30} {'lost':>6} {'seconds':>8}")
    for name, (lost, secs) in rows:
        print(f"{name:<30} {lost:>6} {secs:>8.0f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
