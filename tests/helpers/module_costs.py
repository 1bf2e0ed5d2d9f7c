"""Long-tail scheduling for ``make test`` (issue #42 item 8): the costliest test modules start first.

``make test`` runs ``pytest -n 3 --dist loadfile --no-loadscope-reorder``: each module goes whole to
one worker, in collection order.  xdist's default reorder (by number of tests) let a module of few
slow tests (the browser page, the simulator-driven accuracy checks) start last and run alone at the
end.  Here the collected items are sorted by their module's cost, dearest first, from the checked-in
table ``module_costs.json`` (seconds of test time per module, one worker, idle machine); a module
not in the table (a new one) is placed as if it cost ``UNKNOWN_QUANTILE`` of the table, so a heavy
newcomer is not left for the end and a light one delays the heavy ones little.  The order within a
module is kept, and the ordering only changes when tests run, never what they assert.

Each run records what each module really cost in pytest's cache (``oarmreg/module_cost_s``);
``python -m tests.helpers.module_costs`` prints the table from that record, to refresh the JSON
after a full run (``--write`` writes it).
"""

from __future__ import annotations

import json
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Protocol

TABLE = Path(__file__).with_name("module_costs.json")
CACHE_KEY = "oarmreg/module_cost_s"
UNKNOWN_QUANTILE = 0.75
"""Where a module missing from the table is placed: as if it cost this quantile of the known ones."""


class _Item(Protocol):
    nodeid: str


def module_of(nodeid: str) -> str:
    """``tests/x/test_y.py::test_z[1]`` → ``tests/x/test_y.py``."""
    return nodeid.split("::", 1)[0]


def load_table(path: Path = TABLE) -> dict[str, float]:
    if not path.is_file():
        return {}
    raw = json.loads(path.read_text())
    return {str(k): float(v) for k, v in raw.items()}


def unknown_cost(table: Mapping[str, float]) -> float:
    if not table:
        return 0.0
    costs = sorted(table.values())
    return costs[min(len(costs) - 1, int(UNKNOWN_QUANTILE * len(costs)))]


def order_by_cost(items: Sequence[_Item], table: Mapping[str, float]) -> list[int]:
    """Indices of ``items`` with modules dearest first, each module's items together and in their
    collected order; ties keep the collection order of the modules."""
    default = unknown_cost(table)
    first: dict[str, int] = {}
    for i, it in enumerate(items):
        first.setdefault(module_of(it.nodeid), i)

    def key(i: int) -> tuple[float, int, int]:
        mod = module_of(items[i].nodeid)
        return (-table.get(mod, default), first[mod], i)

    return sorted(range(len(items)), key=key)


def add_durations(totals: dict[str, float], nodeid: str, duration_s: float) -> None:
    mod = module_of(nodeid)
    totals[mod] = totals.get(mod, 0.0) + duration_s


def main(argv: Sequence[str]) -> int:
    """Print (or ``--write``) the cost table from the last run recorded in .pytest_cache."""
    cache = Path(".pytest_cache/v") / CACHE_KEY
    if not cache.is_file():
        print(f"no {cache}: run the suite first (make test)", file=sys.stderr)
        return 1
    try:
        recorded = json.loads(cache.read_text()).items()
    except (ValueError, AttributeError) as e:  # truncated or not a JSON object
        print(
            f"{cache} is not the record pytest writes ({e}): run the suite again (make test)", file=sys.stderr
        )
        return 1
    # the record keeps every module ever run in this checkout; a moved or deleted one is left out
    measured = {k: round(float(v), 1) for k, v in recorded if Path(k).is_file()}
    text = json.dumps(dict(sorted(measured.items(), key=lambda kv: -kv[1])), indent=1) + "\n"
    if "--write" in argv:
        TABLE.write_text(text)
    else:
        print(text, end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
