"""Thread pools whose workers live as long as the service (C-STORE decoding, auto-register)."""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

DEADLINE_START_S = 30.0
"""How long starting the executors' workers may take (threads: instant unless the machine is stuck)."""


def started_executor(n_workers: int, thread_name_prefix: str) -> ThreadPoolExecutor:
    """A thread pool with every worker started now (each would start on first busy use), so they all
    live as long as the service: one blocking task per worker until all of them run."""
    ex = ThreadPoolExecutor(n_workers, thread_name_prefix=thread_name_prefix)
    barrier = threading.Barrier(n_workers + 1)
    futures = [ex.submit(barrier.wait, DEADLINE_START_S) for _ in range(n_workers)]
    barrier.wait(DEADLINE_START_S)
    for f in futures:
        f.result()
    return ex
