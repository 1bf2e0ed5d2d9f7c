"""Shared fixtures.  Autouse fixtures fail any test (or module) that leaves threads or tasks behind."""

from __future__ import annotations

import asyncio
import asyncio.tasks
import gc
import logging
import os
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.helpers import module_costs, scan_cache
from tests.helpers.paths import CONFIGS, REPO

__all__ = ["CONFIGS", "REPO"]
LEAK_GRACE_S = 5.0
"""A thread or task still alive this long after its test (or module) ended counts as leaked."""
LEAK_POLL_S = 0.01
"""Poll period while waiting for a finishing task (threads are joined instead)."""

THIRD_PARTY_THREADS: tuple[str, ...] = (
    # anyio's thread pool (Starlette's run_in_threadpool runs sync FastAPI endpoints there) keeps
    # idle "AnyIO worker thread"s for reuse up to 10 s; they belong to the server's event loop,
    # end with it, and the per-module check below (which allows nothing) catches them if not.
    "AnyIO worker thread",
)
"""Name prefixes of long-lived third-party threads that may outlive one test (not a module).
Add a prefix only with a comment naming the library and why the thread is not ours."""


def _pending_tasks() -> set[asyncio.Task[object]]:
    """Every not-yet-done asyncio task, on any event loop in any thread.

    CPython 3.11/3.12 register each task in the weak set ``asyncio.tasks._all_tasks``
    (``asyncio.all_tasks`` reads the same set, filtered to one loop); elsewhere fall back to
    scanning the garbage collector's objects.
    """
    registry = getattr(asyncio.tasks, "_all_tasks", None)
    if registry is not None:
        candidates: list[object] = list(registry)
    else:  # pragma: no cover - other interpreters
        candidates = [o for o in gc.get_objects() if isinstance(o, asyncio.Task)]
    return {t for t in candidates if isinstance(t, asyncio.Task) and not t.done()}


def _leaks(
    threads_before: set[threading.Thread], tasks_before: set[asyncio.Task[object]], allowed: tuple[str, ...]
) -> tuple[list[threading.Thread], list[asyncio.Task[object]]]:
    """Threads (daemons included, names starting with ``allowed`` excepted) and tasks new since before."""
    threads = [
        t
        for t in threading.enumerate()
        if t not in threads_before and t.is_alive() and not t.name.startswith(allowed)
    ]
    tasks = [t for t in _pending_tasks() if t not in tasks_before]
    return threads, tasks


def _assert_nothing_left(
    threads_before: set[threading.Thread],
    tasks_before: set[asyncio.Task[object]],
    what: str,
    allowed: tuple[str, ...] = (),
) -> None:
    """Wait up to LEAK_GRACE_S for new threads to end and new tasks to finish, then fail naming them."""
    deadline = time.monotonic() + LEAK_GRACE_S
    while True:
        threads, tasks = _leaks(threads_before, tasks_before, allowed)
        if not (threads or tasks) or time.monotonic() > deadline:
            break
        if threads:
            threads[0].join(timeout=LEAK_POLL_S)
        else:
            threading.Event().wait(LEAK_POLL_S)
    names = [f"{t.name}{' (daemon)' if t.daemon else ''}" for t in threads]
    coros = [f"{t.get_name()}: {t.get_coro()!r}" for t in tasks]
    assert not (threads or tasks), f"{what} left threads running: {names}; asyncio tasks pending: {coros}"


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Dearest modules first (tests/helpers/module_costs.py), so no slow module starts last."""
    order = module_costs.order_by_cost(items, module_costs.load_table())
    items[:] = [items[i] for i in order]


_MODULE_TIME_S: dict[str, float] = {}


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    """Add up each module's setup, call and teardown time (on xdist's controller: all workers')."""
    module_costs.add_durations(_MODULE_TIME_S, report.nodeid, report.duration)


ONE_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "OPENCV_FOR_THREADS_NUM")
"""Thread pools of the numeric libraries (OpenBLAS, OpenMP, OpenCV's ``parallel_for``), held to one
thread in the test processes and the services and CLIs they start (issue #42 item 8).  ``make test``
already runs three processes on CI's two cores; a second level of threads inside each only spins:
the ``demo`` preset's simulation took 12.2 s of CPU with the default pools against 8.9 s with one
thread each, in the same 8.7 s of wall time on an idle machine.  Set on the controller before
xdist starts its workers (they inherit it; under ``-n 0`` only the processes a test starts do); a
variable already set is left as it is."""


def pytest_configure(config: pytest.Config) -> None:
    """The controller names the run's simulated-scan cache and holds the numeric libraries to one
    thread (:data:`ONE_THREAD_VARIABLES`) before xdist starts its workers."""
    if not hasattr(config, "workerinput"):
        scan_cache.init_run_cache()
        for name in ONE_THREAD_VARIABLES:
            os.environ.setdefault(name, "1")


def pytest_collection_finish(session: pytest.Session) -> None:
    """Move what collection built (every imported module, the test items, hypothesis' strategies) out
    of the garbage collector's view: it lives for the whole run, and the full collections of a worker
    would otherwise walk it again each time (issue #42 item 8; a ``gc.callbacks`` timer over
    tests/unit, tests/property and tests/integration on 3 workers: 7.8 s in the collector without
    this, 6.3 s with it)."""
    gc.collect()
    gc.freeze()


def pytest_sessionfinish(session: pytest.Session) -> None:
    """Record what each module cost in this run, over the record of earlier runs (not on xdist
    workers: the controller has it all); remove the run's simulated-scan cache."""
    if not hasattr(session.config, "workerinput"):
        scan_cache.remove_run_cache()
    cache = getattr(session.config, "cache", None)  # None under -p no:cacheprovider
    if _MODULE_TIME_S and cache is not None and not hasattr(session.config, "workerinput"):
        cache.set(module_costs.CACHE_KEY, {**cache.get(module_costs.CACHE_KEY, {}), **_MODULE_TIME_S})


@pytest.fixture(autouse=True, scope="module")
def no_leaks_after_module(request: pytest.FixtureRequest) -> Iterator[None]:
    """Module-scoped fixtures (servers shared by a module's tests) must stop what they started.

    Autouse, so it is set up before and torn down after the module's other module-scoped fixtures.
    """
    threads_before, tasks_before = set(threading.enumerate()), _pending_tasks()
    yield
    _assert_nothing_left(threads_before, tasks_before, f"module {request.node.name}")


@pytest.fixture(autouse=True)
def no_leaks(request: pytest.FixtureRequest) -> Iterator[None]:
    """Each test must stop every thread and task it started (fixtures of wider scope are already up)."""
    threads_before, tasks_before = set(threading.enumerate()), _pending_tasks()
    yield
    _assert_nothing_left(threads_before, tasks_before, f"test {request.node.name}", THIRD_PARTY_THREADS)


@pytest.fixture(autouse=True)
def no_stale_log_handlers() -> Iterator[None]:
    """``service.cli.main.main`` (called in-process by many tests) puts a ``StreamHandler`` on the root
    logger bound to the ``sys.stderr`` of that moment, pytest's capture, which is closed after the
    test: a later log line from a thread of a longer-lived fixture then prints "Logging error".
    Remove the plain stream handlers a test added and put the root level back."""
    root = logging.getLogger()
    before, level = set(root.handlers), root.level
    yield
    added = [h for h in root.handlers if h not in before and type(h) is logging.StreamHandler]
    for h in added:
        root.removeHandler(h)
    if added:
        root.setLevel(level)


@pytest.fixture(scope="session")
def phantom_path() -> Path:
    return CONFIGS / "phantoms" / "bai2018_cube.toml"


@pytest.fixture(scope="session")
def phantom(phantom_path: Path):  # type: ignore[no-untyped-def]
    from registration.model.phantom import load_phantom

    return load_phantom(phantom_path)


@pytest.fixture(scope="session")
def ref_client(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The reference OpenIGTLink library's client (tests/helpers/igtl_ref.py), built once per session."""
    from tests.helpers.igtl_ref import build_ref_client

    return build_ref_client(tmp_path_factory.mktemp("igtl-ref"))
