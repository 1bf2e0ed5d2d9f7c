"""``oarmreg`` commands share helpers through modules of their own (``argtypes``, ``scan_inputs``,
``demo_report``), never by importing another command (issue 44: ``register`` imported ``calibrate``,
``verify`` imported ``register``)."""

from __future__ import annotations

import ast
from pathlib import Path

COMMANDS = Path(__file__).resolve().parents[4] / "service" / "cli" / "commands"
ALLOWED = {("demo", "serve")}
"""``demo`` runs the service in a thread exactly as the tests and ``serve`` do (``serve_in_thread``)."""


def _is_command(path: Path) -> bool:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    return any(isinstance(n, ast.FunctionDef) and n.name == "run" for n in tree.body)


def test_no_command_imports_another_command() -> None:
    commands = {p.stem for p in COMMANDS.glob("*.py") if _is_command(p)}
    assert {"register", "verify", "calibrate", "detect", "serve"} <= commands
    found = []
    for name in sorted(commands):
        for node in ast.walk(ast.parse((COMMANDS / f"{name}.py").read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("service.cli.commands."):
                other = (node.module or "").rsplit(".", 1)[1]
                if other in commands and (name, other) not in ALLOWED:
                    found.append(f"{name} imports {other} (line {node.lineno})")
    assert found == [], f"move the shared helper into a module of its own (scan_inputs, argtypes): {found}"
