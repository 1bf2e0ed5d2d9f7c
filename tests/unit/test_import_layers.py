"""Layering of the packages, checked on the source (``ast``), not by importing anything.

* ``registration/`` is pure: it imports neither ``service`` nor ``drivers`` (design.md §2);
  ``drivers/`` imports neither ``service`` nor ``registration``; ``dicomnet/`` (the DICOM networking
  the service, the mocks and the test peers share) imports no other package of the project.
* No import cycle among the modules of ``service/`` or of ``drivers/``, counting imports inside
  functions and ``TYPE_CHECKING`` blocks too: a lazy import hides a cycle, it does not remove it.
* ``service/http/api/*`` never imports ``service.http.app`` (the routes get the context from
  :mod:`service.runtime.context`).
* ``service/`` is rooms along the data's way (design.md §2): a room imports only the shared top
  level and the rooms before it in :data:`SERVICE_ROOMS`; the shared top level imports no room; the
  top level holds at most :data:`MAX_TOP_LEVEL_MODULES` modules and every room's ``__init__`` says
  what enters it and what leaves it.
* Production code imports ``mocks`` only in the commands that exist to run mocks
  (:data:`MOCK_COMMANDS`); ``mocks`` itself never imports ``service``.
* No module reads another module's private name (issue #35): ``from pkg.mod import _name``
  (absolute or relative) or ``mod._name`` on an imported project module. A helper two modules
  share is public in its module (or the two are one module).
* ``from pkg import name`` runs ``pkg/__init__.py`` and reads ``name`` from it, so it counts as an
  import of the package too: a package ``__init__`` that imports a module importing the package
  that way is a cycle (``import pkg.mod`` / ``from pkg.mod import x`` are not).
"""

from __future__ import annotations

import ast
import functools
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("registration", "drivers", "dicomnet", "service", "mocks")
MOCK_COMMANDS = frozenset(
    {
        "service.cli.commands.demo",
        "service.cli.commands.demo_calibrate",
        "service.cli.commands.simulate",
        "service.cli.commands.mock",
        "service.cli.commands.send",  # the mock O-arm's C-STORE push, to test a listener (issue 42)
    }
)
"""The only production modules that may import ``mocks``: the commands that run the mocks."""


SERVICE_ROOMS = ("store", "intake", "registrations", "navigation", "runtime", "http", "cli")
"""The rooms of ``service/`` in the order of the data's way: each may import the ones before it."""
MAX_TOP_LEVEL_MODULES = 12
"""Issue #35: ``service/`` has at most 12 top-level modules (``__init__`` included)."""


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def all_modules() -> dict[str, Path]:
    return {module_name(p): p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))}


def imports_of(path: Path, known: set[str]) -> set[str]:
    """Project modules ``path`` imports (``from pkg import submodule`` counts as the submodule)."""
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)  # its __init__ runs and each name is read from it
            out.update(f"{node.module}.{a.name}" for a in node.names)
    return {m for m in out if m in known}


def is_private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def imported_module(module: str, is_package: bool, node: ast.ImportFrom) -> str:
    """The module a ``from ... import`` in ``module`` reads from, relative imports resolved."""
    if node.level == 0:
        return node.module or ""
    base = module.split(".") if is_package else module.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join([*base, *([node.module] if node.module else [])])


def private_imports(path: Path, module: str, known: set[str]) -> list[str]:
    """Where ``path`` (the module ``module``) reads a private name of another project module."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    is_package = path.name == "__init__.py"
    bound: dict[str, str] = {}  # local name -> the project module it is bound to
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name in known:
                    bound[a.asname or a.name] = a.name
        elif isinstance(node, ast.ImportFrom):
            source = imported_module(module, is_package, node)
            if source.split(".")[0] not in PACKAGES:
                continue
            for a in node.names:
                if is_private(a.name):
                    out.append(f"{module}:{node.lineno} from {source} import {a.name}")
                elif f"{source}.{a.name}" in known:
                    bound[a.asname or a.name] = f"{source}.{a.name}"
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and is_private(node.attr):
            owner = bound.get(ast.unparse(node.value))
            if owner is not None and owner != module:
                out.append(f"{module}:{node.lineno} {owner}.{node.attr}")
    return sorted(out)


@functools.cache  # parsed once per run: the tests only read it
def graph() -> dict[str, set[str]]:
    mods = all_modules()
    known = set(mods)
    return {name: imports_of(path, known) for name, path in mods.items()}


def find_cycle(g: dict[str, set[str]], nodes: set[str]) -> list[str] | None:
    """One import cycle among ``nodes`` (as a list of modules, first = last), or None."""
    state: dict[str, int] = {}  # 1: on the stack, 2: done
    stack: list[str] = []

    def visit(n: str) -> list[str] | None:
        state[n] = 1
        stack.append(n)
        for m in sorted(g[n] & nodes):
            if state.get(m) == 1:
                return [*stack[stack.index(m) :], m]
            if m not in state and (found := visit(m)) is not None:
                return found
        stack.pop()
        state[n] = 2
        return None

    for n in sorted(nodes):
        if n not in state and (found := visit(n)) is not None:
            return found
    return None


def in_package(g: dict[str, set[str]], pkg: str) -> Iterator[str]:
    return (m for m in g if m == pkg or m.startswith(pkg + "."))


def test_the_checker_finds_a_cycle() -> None:
    g = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert find_cycle(g, set(g)) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}, {"a", "b"}) is None


def test_from_package_import_counts_as_importing_the_package(tmp_path: Path) -> None:
    """``pkg/__init__.py`` importing ``pkg.db``, which does ``from pkg import util``: a cycle
    through the package ``__init__``; ``import pkg.util`` in ``pkg.db`` is none."""
    known = {"pkg", "pkg.db", "pkg.util"}
    init, db = tmp_path / "init.py", tmp_path / "db.py"
    init.write_text("from pkg.db import Database\n")
    db.write_text("from pkg import util\n")
    g = {"pkg": imports_of(init, known), "pkg.db": imports_of(db, known), "pkg.util": set()}
    assert find_cycle(g, known) == ["pkg", "pkg.db", "pkg"]
    db.write_text("import pkg.util\n")
    g["pkg.db"] = imports_of(db, known)
    assert find_cycle(g, known) is None


@pytest.mark.parametrize("pkg", ["service", "drivers", "dicomnet", "registration", "mocks"])
def test_no_import_cycle(pkg: str) -> None:
    g = graph()
    cycle = find_cycle(g, set(in_package(g, pkg)))
    assert cycle is None, "import cycle: " + " → ".join(cycle or [])


@pytest.mark.parametrize(
    ("pkg", "forbidden"),
    [
        ("registration", ("service", "drivers", "dicomnet", "mocks")),
        ("drivers", ("service", "registration", "mocks", "dicomnet")),
        ("dicomnet", ("service", "registration", "drivers", "mocks")),
        ("mocks", ("service",)),
    ],
)
def test_lower_layers_do_not_import_upper_ones(pkg: str, forbidden: tuple[str, ...]) -> None:
    g = graph()
    bad = sorted(
        f"{m} imports {dep}"
        for m in in_package(g, pkg)
        for dep in g[m]
        if any(dep == f or dep.startswith(f + ".") for f in forbidden)
    )
    assert bad == []


def test_api_does_not_import_the_app() -> None:
    g = graph()
    bad = sorted(m for m in in_package(g, "service.http.api") if "service.http.app" in g[m])
    assert bad == []


def test_production_code_imports_mocks_only_in_the_mock_commands() -> None:
    g = graph()
    bad = sorted(
        f"{m} imports {dep}"
        for pkg in ("service", "drivers", "dicomnet", "registration")
        for m in in_package(g, pkg)
        if m not in MOCK_COMMANDS
        for dep in g[m]
        if dep == "mocks" or dep.startswith("mocks.")
    )
    assert bad == []


def room_of(module: str) -> str | None:
    """``service.intake.watcher`` -> ``intake``; a module of the shared top level -> ``""``."""
    parts = module.split(".")
    if parts[0] != "service":
        return None
    return parts[1] if len(parts) > 2 or (len(parts) == 2 and parts[1] in SERVICE_ROOMS) else ""


def room_violations(g: dict[str, set[str]]) -> list[str]:
    rank = {room: i for i, room in enumerate(SERVICE_ROOMS)}
    bad = []
    for m, deps in g.items():
        src = room_of(m)
        if src is None:
            continue
        for dep in deps:
            dst = room_of(dep)
            if dst is None or dst == src or dst == "":
                continue
            if src == "" or rank[dst] > rank[src]:
                bad.append(f"{m} ({src or 'top level'}) imports {dep} ({dst})")
    return sorted(bad)


def test_the_room_checker_finds_an_upward_import() -> None:
    g = {
        "service.intake.watcher": {"service.store.base", "service.events"},
        "service.store.base": {"service.intake.watcher"},
        "service.events": {"service.http.app"},
        "service.http.app": set(),
    }
    assert room_violations(g) == [
        "service.events (top level) imports service.http.app (http)",
        "service.store.base (store) imports service.intake.watcher (intake)",
    ]


def test_service_rooms_import_only_the_rooms_before_them() -> None:
    assert room_violations(graph()) == []


def test_service_top_level_is_small_and_every_room_says_what_enters_and_leaves() -> None:
    top = sorted(p.name for p in (ROOT / "service").glob("*.py"))
    assert len(top) <= MAX_TOP_LEVEL_MODULES, top
    rooms = sorted(p.name for p in (ROOT / "service").iterdir() if (p / "__init__.py").is_file())
    assert sorted(SERVICE_ROOMS) == rooms
    for init in sorted((ROOT / "service").rglob("__init__.py")):  # the rooms and every sub-package
        doc = ast.get_docstring(ast.parse(init.read_text()))
        assert doc and "Enters:" in doc and "Leaves:" in doc, f"{init.relative_to(ROOT)}: {doc!r}"


def test_the_private_import_checker_finds_absolute_relative_and_attribute_reads(tmp_path: Path) -> None:
    known = {"registration", "registration.calibration", "registration.calibration.fit"}
    src = tmp_path / "solver.py"
    src.write_text(
        "from registration.calibration.fit import _fit, fit\n"
        "from .fit import _per_pose\n"
        "from . import fit as f\n"
        "import registration.calibration.fit\n"
        "from numpy import _private_numpy_name\n"
        "from registration.calibration.fit import __all__\n"
        "f._prior_weights(registration.calibration.fit._leave_one_out, f.public)\n"
    )
    assert private_imports(src, "registration.calibration.solver", known) == [
        "registration.calibration.solver:1 from registration.calibration.fit import _fit",
        "registration.calibration.solver:2 from registration.calibration.fit import _per_pose",
        "registration.calibration.solver:7 registration.calibration.fit._leave_one_out",
        "registration.calibration.solver:7 registration.calibration.fit._prior_weights",
    ]


def test_no_module_imports_another_modules_private_name() -> None:
    """Issue #35 counted 58 such imports across 16 files (60 when this test was written)."""
    mods = all_modules()
    known = set(mods)
    bad = [line for name, path in mods.items() for line in private_imports(path, name, known)]
    assert bad == []


PART_CONSTRUCTORS = frozenset(
    {
        "Orchestrator", "CalibrationJobs", "Capture", "Intake", "ScanLifecycle", "SeriesWatcher",
        "CStoreIntake", "IgtlPublisher", "PacsExporter", "AutoRegister",
    }
)  # fmt: skip
"""The service's parts (issue 44: the runtime starts them; HTTP is one door, not the house)."""


def test_no_module_in_http_starts_a_part_of_the_service() -> None:
    started: list[str] = []
    for name, path in sorted(all_modules().items()):
        if not name.startswith("service.http"):
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Call):
                f = node.func
                called = f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else ""
                if called in PART_CONSTRUCTORS or (called == "open" and ast.unparse(f) == "Database.open"):
                    started.append(f"{name}:{node.lineno} {ast.unparse(f)}(…)")
    assert started == [], f"start the service's parts in service.runtime.assembly, not in HTTP: {started}"
