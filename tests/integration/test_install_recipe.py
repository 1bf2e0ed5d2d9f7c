"""docs/operations.md "Install", run as written in a temporary root (issue 34, item 1).

The recipe's block is extracted from the doc; its absolute paths are moved under a temporary
root, the steps that need root powers on the real machine (``apt-get``, ``useradd``, owners and
groups, ``systemctl``) are left out, and the venv borrows this project's installed dependencies
(as .ci/wheel-smoke does) so no network is needed.  Everything else runs as written, from a wheel
built by the recipe's own command in a copy of the checkout: the installed ``oarmreg config check``
must pass on the copied TOML, and the unit's Documentation= file must exist.
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
    sees the dependencies without a download (the method of .ci/wheel-smoke)."""
    dirs = list(dict.fromkeys(sysconfig.get_path(k) for k in ("purelib", "platlib")))
    lines = list(dirs)
    for d in dirs:
        for f in sorted(Path(d).glob("*.pth")):
            if not f.name.startswith("__editable__") and f.name != "distutils-precedence.pth":
                lines += [ln for ln in f.read_text().splitlines() if ln.strip()]
    return "\n".join(lines) + "\n"


@pytest.mark.slow  # builds a wheel: ~85 s on an idle 2-core machine, more when loaded
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
