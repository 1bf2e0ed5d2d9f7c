"""docs/operations.md "Install", run as written in a temporary root (issue 34, item 1), and the
wheel smoke test (issue #9 item 6) on what it installed.

The recipe's block is extracted from the doc; its absolute paths are moved under a temporary
root, the steps that need root powers on the real machine (``apt-get``, ``useradd``, owners and
groups, ``systemctl``) are left out, and the venv borrows this project's installed dependencies
(``_project_deps_pth``) so no network is needed.  Everything else runs as written, from a wheel
built by the recipe's own command in a copy of the checkout: the installed ``oarmreg config check``
must pass on the copied TOML, and the unit's Documentation= file must exist.  Then, from another
folder with nothing of the checkout on the path, the installed wheel imports its packages and configs
from its own site folder, loads both robot models, and simulates a scan and detects its spheres
(within 0.5 mm of the truth): a module, URDF, phantom or TOML that only a source checkout has
fails here.  It is the suite's one wheel build (``make wheel-smoke`` runs it alone).
"""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

from tests.helpers.paths import REPO

DOC = REPO / "docs" / "operations.md"
ROOTED = ("/opt/", "/etc/", "/var/lib/", "/srv/", "/usr/share/")
NEEDS_ROOT = ("apt-get ", "useradd ", "systemctl ", "journalctl ", "chgrp ", "chown ")


def recipe() -> list[str]:
    text = DOC.read_text(encoding="utf-8")
    m = re.search(r"```sh\n(.*?)```", text[text.index("<!-- install-recipe") :], re.S)
    assert m, "no sh block after the install-recipe marker"
    return [ln for ln in m.group(1).splitlines() if ln.strip() and not ln.lstrip().startswith("#")]


def rooted(line: str, root: Path) -> str:
    for prefix in ROOTED:
        line = re.sub(rf"(?<![\w.$]){re.escape(prefix)}", f"{root}{prefix}", line)
    return re.sub(r"\s-[og] oarmreg\b", "", line)


def _project_deps_pth() -> str:
    """The project venv's site folders and its .pth lines (not the editable hook): the fresh venv
    sees the dependencies without a download; the wheel itself is installed with --no-deps."""
    dirs = list(dict.fromkeys(sysconfig.get_path(k) for k in ("purelib", "platlib")))
    lines = list(dirs)
    for d in dirs:
        for f in sorted(Path(d).glob("*.pth")):
            if not f.name.startswith("__editable__") and f.name != "distutils-precedence.pth":
                lines += [ln for ln in f.read_text().splitlines() if ln.strip()]
    return "\n".join(lines) + "\n"


@pytest.mark.slow  # builds the suite's one wheel (it replaced .ci/wheel-smoke)
@pytest.mark.timeout(600)
def test_the_install_recipe_gives_a_config_that_passes_its_check(tmp_path: Path) -> None:
    root, src = tmp_path / "root", tmp_path / "src"
    root.mkdir()
    src.mkdir()
    files = subprocess.run(
        ["git", "-C", str(REPO), "ls-files", "-co", "--exclude-standard", "-z"],
        capture_output=True, check=True,
    ).stdout  # fmt: skip
    subprocess.run(
        f"tar -cf - --null -T - | tar -xf - -C {shlex.quote(str(src))}",
        shell=True, input=files, cwd=REPO, check=True,
    )  # fmt: skip
    py = shlex.quote(sys.executable)
    base = shlex.quote(getattr(sys, "_base_executable", sys.executable))
    venv = root / "opt" / "oarmreg"
    script: list[str] = []
    for line in recipe():
        if line.startswith(NEEDS_ROOT):
            continue
        line = rooted(line, root)
        if line.startswith("python3 -m venv "):
            target = line.split()[-1]
            site = f"$({target}/bin/python -c 'import sysconfig; print(sysconfig.get_path(\"purelib\"))')"
            line = f'{base} -m venv --without-pip {target} && cp deps.pth "{site}/_project_deps.pth"'
        elif re.match(r"\S+/bin/pip install ", line):
            line = re.sub(
                r"^(\S+)/bin/pip install ", rf"{py} -m pip --python \1/bin/python install --no-deps ", line
            )
        elif line.startswith("python3 -m pip "):
            line = py + line.removeprefix("python3")
        script.append(line)
    (src / "deps.pth").write_text(_project_deps_pth())
    done = subprocess.run(
        ["bash", "-euo", "pipefail", "-c", "\n".join(script)],
        cwd=src, capture_output=True, text=True, timeout=580, check=False,
        env={"PATH": "/usr/bin:/bin", "HOME": str(tmp_path)},
    )  # fmt: skip
    assert done.returncode == 0, f"{done.stdout[-2000:]}\n{done.stderr[-3000:]}"
    assert (venv / "bin" / "oarmreg").is_file()
    # the unit's Documentation= names a file the recipe installed
    unit = (root / "etc" / "systemd" / "system" / "oarmreg.service").read_text()
    docs = re.findall(r"^Documentation=file://(\S+)", unit, re.M)
    assert docs and all((root / d.lstrip("/")).is_file() for d in docs), docs
    # the copied TOML works from its new folder: config check from the wheel, exit 0
    toml = root / "etc" / "oarmreg" / "oarmreg.toml"
    assert "phantom_file = " not in re.sub(r"#.*", "", toml.read_text())
    check = subprocess.run(
        [str(venv / "bin" / "oarmreg"), "config", "check", "--config", str(toml)],
        cwd=tmp_path, capture_output=True, text=True, timeout=120, check=False,
        env={"PATH": "/usr/bin:/bin", "HOME": str(tmp_path)},
    )  # fmt: skip
    assert check.returncode == 0, check.stderr
    assert str(root / "srv" / "oarm-export") in check.stdout
    _smoke_the_installed_wheel(venv, tmp_path / "run")


SMOKE_IMPORTS = """
import sys
from pathlib import Path

import dicomnet.scu
import oarmreg_configs
import registration
from registration.io.resources import configs_dir, default_phantom
from registration.model.kinematics import RobotModel

site = Path(sys.prefix).resolve()
for mod in (registration, dicomnet.scu, oarmreg_configs):
    where = Path(mod.__file__).resolve()
    assert where.is_relative_to(site), f"{mod.__name__} imported from {where}, not from the wheel in {site}"
assert configs_dir().is_relative_to(site), configs_dir()
assert default_phantom().is_file(), default_phantom()
for name in ("tx60", "tx2_60"):
    RobotModel.load(name)
"""


def _smoke_the_installed_wheel(venv: Path, run: Path) -> None:
    """The installed wheel on its own: packages and configs from its site folder, simulate + detect."""
    import json

    import numpy as np

    run.mkdir()
    env = {"PATH": "/usr/bin:/bin", "HOME": str(run)}

    def call(*argv: str) -> str:
        done = subprocess.run(
            argv, cwd=run, capture_output=True, text=True, timeout=300, check=False, env=env
        )
        assert done.returncode == 0, f"{argv}: {done.stderr[-3000:]}"
        return done.stdout

    call(str(venv / "bin" / "python"), "-c", SMOKE_IMPORTS)
    call(str(venv / "bin" / "oarmreg"), "simulate", "--preset", "small", "--out", "scan")
    call(str(venv / "bin" / "oarmreg"), "detect", "scan", "--json", "detect.json")
    found = np.array([s["center_mm"] for s in json.loads((run / "detect.json").read_text())["spheres"]])
    truth = np.array(json.loads((run / "scan" / "truth.json").read_text())["spheres_image_mm"])
    found, truth = found.reshape(-1, 3), truth.reshape(-1, 3)
    assert len(found) == len(truth), f"detect from the wheel: {len(found)} spheres for {len(truth)} true"
    nearest_mm = np.linalg.norm(truth[:, None] - found[None], axis=2).min(axis=1)
    assert nearest_mm.max() < 0.5, f"detect from the wheel: worst {nearest_mm.max():.3f} mm"
