"""The docs checked where a machine can (issue 34, item 6): docs/cli.md against argparse, the
shipped TOML's commented settings against service/settings.py, every file a doc links."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from tests.helpers.paths import REPO

CLI_MD = REPO / "docs" / "cli.md"
TOML = REPO / "configs" / "oarmreg.toml"


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _commands() -> dict[str, argparse.ArgumentParser]:
    """``"calibrate plan"`` → its parser, for every command and sub-command."""
    from service.cli.main import build_parser

    out: dict[str, argparse.ArgumentParser] = {}

    def walk(prefix: str, parser: argparse.ArgumentParser) -> None:
        for name, p in _subparsers(parser).items():
            out[prefix + name] = p
            walk(f"{prefix}{name} ", p)

    walk("", build_parser())
    return out


def _flags(parser: argparse.ArgumentParser) -> set[str]:
    return {s for a in parser._actions for s in a.option_strings if s.startswith("--")}


def test_cli_md_names_every_command_and_subcommand() -> None:
    text = CLI_MD.read_text(encoding="utf-8")
    commands = _commands()
    leaves = [c for c in commands if not _subparsers(commands[c])]
    missing = [c for c in leaves if f"oarmreg {c}" not in text]
    assert not missing, f"docs/cli.md does not document: {missing}"


def test_every_flag_cli_md_mentions_exists() -> None:
    known = set().union(*(_flags(p) for p in _commands().values())) | {"--help", "--version"}
    text = CLI_MD.read_text(encoding="utf-8")
    mentioned = set(re.findall(r"(?<![\w-])(--[a-z][a-z0-9-]*)", text))
    assert not mentioned - known, f"docs/cli.md names flags no command has: {sorted(mentioned - known)}"


def test_every_setting_in_the_toml_comments_exists() -> None:
    from service.settings import _setting_keys

    known = _setting_keys()
    section, unknown = "", []
    for line in TOML.read_text(encoding="utf-8").splitlines():
        if m := re.match(r"^\s*#?\s*\[([a-z_.]+)\]\s*$", line):
            section = m.group(1) + "."
            continue
        if m := re.match(r"^#\s?([a-z_]+)\s*=\s*\S", line):  # a commented-out setting
            key = section + m.group(1)
            if key not in known:
                unknown.append(key)
    assert not unknown, f"configs/oarmreg.toml comments name unknown settings: {unknown}"


def _doc_files() -> list[Path]:
    return [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md")), *sorted(REPO.glob("*.md"))]


def test_every_file_a_doc_links_exists() -> None:
    broken = []
    for doc in dict.fromkeys(_doc_files()):
        text = doc.read_text(encoding="utf-8")
        for target in re.findall(r"\]\(([^)\s]+)\)", text):
            path = target.split("#", 1)[0]
            if not path or re.match(r"^[a-z]+:", path):
                continue
            if not (doc.parent / path).exists():
                broken.append(f"{doc.relative_to(REPO)} -> {target}")
    assert not broken, broken


def test_no_doc_cites_a_research_note_missing_from_the_repository() -> None:
    cited = []
    for doc in dict.fromkeys(_doc_files()):
        if doc.name == "research-notes.md":  # names the originals it summarises
            continue
        for ref in re.findall(r"research/[\w.-]+\.md", doc.read_text(encoding="utf-8")):
            if not (REPO / ref).exists() and not (doc.parent / ref).exists():
                cited.append(f"{doc.relative_to(REPO)}: {ref}")
    assert not cited, cited
