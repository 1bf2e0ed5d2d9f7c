"""Where the shipped configuration files are: ``configs/`` in a checkout, package data in a wheel.

The repository keeps one copy of each file in ``configs/`` (the place a user
edits).  ``pyproject.toml`` maps that folder into the wheel as the package
``oarmreg_configs`` (setuptools ``package-dir``), so an installed copy reads
the same files through :mod:`importlib.resources`.

Lookup order:

1. ``configs/`` beside this package, when it holds ``oarmreg.toml`` (a source
   checkout, run from the checkout or through an editable install);
2. the installed package ``oarmreg_configs`` (a wheel).

Every function returns a real filesystem :class:`~pathlib.Path`: Pinocchio and
the settings loader need one.  A zipped install (files not on disk) raises
:class:`~registration.errors.ConfigError`.
"""

from __future__ import annotations

import importlib.resources
from pathlib import Path

from registration.errors import ConfigError

CONFIGS_PACKAGE = "oarmreg_configs"
"""Import name of ``configs/`` inside the wheel (``[tool.setuptools.package-dir]``)."""

SERVICE_TOML = "oarmreg.toml"
DEFAULT_PHANTOM_NAME = "bai2018_cube"
_CHECKOUT_CONFIGS = Path(__file__).resolve().parents[2] / "configs"
"""``configs/`` of a source checkout (this file is ``registration/io/resources.py``)."""


def configs_dir() -> Path:
    """The folder holding ``oarmreg.toml``, ``robots/`` and ``phantoms/``.

    Raises
    ------
    ConfigError
        Neither a checkout's ``configs/`` nor the ``oarmreg_configs`` package is there,
        or the package is not on the filesystem (zipped install).
    """
    if (_CHECKOUT_CONFIGS / SERVICE_TOML).is_file():
        return _CHECKOUT_CONFIGS
    try:
        root = importlib.resources.files(CONFIGS_PACKAGE)
    except ModuleNotFoundError:
        raise ConfigError(
            f"configuration files not found: expected {_CHECKOUT_CONFIGS} (source checkout) or the "
            f"installed package {CONFIGS_PACKAGE!r} (wheel); reinstall oarmreg"
        ) from None
    if not isinstance(root, Path):
        raise ConfigError(
            f"package {CONFIGS_PACKAGE!r} is not on the filesystem ({root!r}); install oarmreg unzipped"
        )
    return root


def config_path(*parts: str) -> Path:
    """A file or folder under :func:`configs_dir`, e.g. ``config_path("robots", "tx60.urdf")``.

    The path is returned whether or not it exists; callers report a missing file themselves.
    """
    return configs_dir().joinpath(*parts)


def robots_dir() -> Path:
    """The folder of the project's URDFs (``configs/robots``)."""
    return config_path("robots")


def robot_urdf(name: str) -> Path:
    """The URDF of a named robot model (``"tx60"`` → ``configs/robots/tx60.urdf``); may not exist."""
    return robots_dir() / f"{name}.urdf"


def default_phantom() -> Path:
    """The default phantom definition, ``configs/phantoms/bai2018_cube.toml``."""
    return config_path("phantoms", f"{DEFAULT_PHANTOM_NAME}.toml")
