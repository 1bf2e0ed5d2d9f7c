"""The suite's long-tail ordering (tests/helpers/module_costs.py, issue #42 item 8)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.helpers import module_costs as mc


@dataclass
class _It:
    nodeid: str


def _modules(items: list[_It], order: list[int]) -> list[str]:
    out: list[str] = []
    for i in order:
        m = mc.module_of(items[i].nodeid)
        if not out or out[-1] != m:
            out.append(m)
    return out


def test_dearest_module_first_each_module_whole_and_in_its_own_order() -> None:
    items = [_It(f"tests/{m}.py::t{i}") for m in ("cheap", "dear", "mid") for i in range(3)]
    items.insert(1, _It("tests/dear.py::t9"))  # a module's items need not be adjacent when collected
    table = {"tests/cheap.py": 1.0, "tests/dear.py": 50.0, "tests/mid.py": 10.0}
    order = mc.order_by_cost(items, table)
    assert sorted(order) == list(range(len(items)))  # nothing lost, nothing twice
    assert _modules(items, order) == ["tests/dear.py", "tests/mid.py", "tests/cheap.py"]
    dear = [items[i].nodeid for i in order if items[i].nodeid.startswith("tests/dear.py")]
    assert dear == ["tests/dear.py::t9", "tests/dear.py::t0", "tests/dear.py::t1", "tests/dear.py::t2"]


def test_an_unknown_module_is_placed_at_the_tables_upper_quartile() -> None:
    table = {f"tests/m{i}.py": float(i) for i in range(1, 9)}  # 1 … 8 s
    assert mc.unknown_cost(table) == 7.0
    items = [_It(f"{m}::t") for m in table] + [_It("tests/new.py::t")]
    mods = _modules(items, mc.order_by_cost(items, table))
    assert mods[:3] == ["tests/m8.py", "tests/m7.py", "tests/new.py"]  # tied with 7 s: collection order
    assert mc.unknown_cost({}) == 0.0


def test_the_checked_in_table_names_modules_that_exist() -> None:
    """A renamed or deleted module left in the table is harmless but misleading: refresh it."""
    table = mc.load_table()
    assert table and all(v >= 0.0 for v in table.values())
    repo = Path(mc.__file__).resolve().parents[2]
    missing = [m for m in table if not (repo / m).is_file()]
    assert not missing, f"{missing} are gone: python -m tests.helpers.module_costs --write after a full run"
    assert json.loads(mc.TABLE.read_text()) == table


def test_the_refreshed_table_leaves_out_modules_that_are_gone(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """pytest's record keeps every module ever run in a checkout; ``--write`` keeps those that exist."""
    (tmp_path / "tests").mkdir()
    (tmp_path / "tests" / "test_here.py").write_text("")
    record = tmp_path / ".pytest_cache" / "v" / mc.CACHE_KEY
    record.parent.mkdir(parents=True)
    record.write_text(json.dumps({"tests/test_here.py": 3.04, "tests/test_moved_away.py": 9.0}))
    table = tmp_path / "table.json"
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(mc, "TABLE", table)
    assert mc.main(["--write"]) == 0
    assert json.loads(table.read_text()) == {"tests/test_here.py": 3.0}


@pytest.mark.parametrize("text", ['{"tests/test_here.py": 3.', "[1, 2]"])
def test_a_damaged_record_is_refused_with_what_to_do_and_the_table_is_left_alone(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], text: str
) -> None:
    record = tmp_path / ".pytest_cache" / "v" / mc.CACHE_KEY
    record.parent.mkdir(parents=True)
    record.write_text(text)
    table = tmp_path / "table.json"
    table.write_text('{"tests/test_here.py": 1.0}\n')
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(mc, "TABLE", table)
    assert mc.main(["--write"]) == 1
    assert "run the suite again (make test)" in capsys.readouterr().err
    assert table.read_text() == '{"tests/test_here.py": 1.0}\n'
