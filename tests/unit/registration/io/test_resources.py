"""Shipped configuration files are found through registration.io.resources (issue #9 item 6)."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from registration.errors import ConfigError
from registration.io import resources
from registration.model.kinematics import RobotModel
from registration.model.phantom import load_phantom

REPO = Path(__file__).resolve().parents[4]


def test_checkout_configs_are_the_ones_used() -> None:
    assert resources.configs_dir() == REPO / "configs"
    assert resources.robot_urdf("tx60") == REPO / "configs" / "robots" / "tx60.urdf"
    assert resources.default_phantom() == REPO / "configs" / "phantoms" / "bai2018_cube.toml"
    assert load_phantom(resources.default_phantom()).n_spheres == 28


def test_a_checkout_needs_no_installed_package(monkeypatch: pytest.MonkeyPatch) -> None:
    """A source checkout finds its own configs/ (the path was one folder short after the move into
    registration/io/, so every checkout used the installed package: a worktree read the main
    checkout's URDFs through its editable install)."""
    monkeypatch.setattr(resources, "CONFIGS_PACKAGE", "oarmreg_no_such_package")
    assert resources.configs_dir() == REPO / "configs"


def test_named_robot_loads_from_the_resources(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    (tmp_path / "robots").mkdir()
    (tmp_path / "robots" / "other.urdf").write_bytes((REPO / "configs" / "robots" / "tx60.urdf").read_bytes())
    monkeypatch.setattr(resources, "configs_dir", lambda: tmp_path)
    assert RobotModel.load("other").urdf_path == tmp_path / "robots" / "other.urdf"
    with pytest.raises(ConfigError, match=r"unknown robot model 'tx60': expected one of \['other'\]"):
        RobotModel.load("tx60")


def test_installed_package_is_the_fallback(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setattr(resources, "_CHECKOUT_CONFIGS", tmp_path / "no-checkout")
    monkeypatch.setattr(resources, "CONFIGS_PACKAGE", "oarmreg_no_such_package")
    with pytest.raises(ConfigError, match=r"oarmreg_no_such_package.*reinstall oarmreg"):
        resources.configs_dir()


def test_every_package_and_config_file_is_in_the_wheel_list() -> None:
    """pyproject lists packages explicitly (for the oarmreg_configs mapping): none may be forgotten."""
    tool = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    on_disk = {
        ".".join(p.parent.relative_to(REPO).parts)
        for top in ("registration", "drivers", "dicomnet", "service", "mocks")
        for p in (REPO / top).rglob("__init__.py")
    }
    listed = set(tool["packages"])
    assert on_disk <= listed, f"add to [tool.setuptools] packages: {sorted(on_disk - listed)}"
    assert tool["package-dir"] == {"oarmreg_configs": "configs"}
    patterns = tool["package-data"]
    for f in (REPO / "configs").rglob("*"):
        if f.is_file() and f.suffix != ".py" and "__pycache__" not in f.parts:
            rel = f.relative_to(REPO / "configs")
            package = ".".join(("oarmreg_configs", *rel.parent.parts))
            assert any(rel.match(pat) or Path(rel.name).match(pat) for pat in patterns.get(package, [])), (
                f"configs/{rel} is not shipped: add it to package-data of {package}"
            )
