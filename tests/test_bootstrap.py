"""scripts/bootstrap.sh's choice of what to install: the extras asked for (``--extras``, default every extra and the
test tools), beside those already installed while pyproject.toml is unchanged; nothing when they are all there.

The script runs on a copy of pyproject.toml with an empty list of Debian packages; ``.venv/bin/python`` and
``.venv/bin/phantom`` are stand-ins that write down how they were called (pip itself is not run: this is the
script's bookkeeping, not the install, which `make test` does for real)."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def checkout(tmp_path: Path) -> Path:
    (tmp_path / "scripts").mkdir()
    shutil.copy(ROOT / "scripts" / "bootstrap.sh", tmp_path / "scripts" / "bootstrap.sh")
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    (tmp_path / "no-packages.txt").write_text("# nothing to install\n")
    bin_folder = tmp_path / ".venv" / "bin"
    bin_folder.mkdir(parents=True)
    for name in ("python", "phantom"):
        stand_in = bin_folder / name
        stand_in.write_text(f'#!/bin/sh\necho "{name} $*" >> "$(dirname "$0")/../calls.log"\n')
        stand_in.chmod(0o755)
    return tmp_path


def bootstrap(checkout: Path, *arguments: str) -> list[str]:
    """Run the copy's bootstrap.sh; the pip installs it made."""
    log = checkout / ".venv" / "calls.log"
    log.unlink(missing_ok=True)
    result = subprocess.run(["bash", "scripts/bootstrap.sh", *arguments, "no-packages.txt"], cwd=checkout,
                            check=True, capture_output=True, text=True, env={**os.environ, "PYTHON": "python3"})
    assert result.stderr == ""  # a first run, with no stamp yet, included
    calls = log.read_text().splitlines() if log.exists() else []
    return [call.split()[-1] for call in calls if call.startswith("python -m pip install -q --no-compile")]


def test_the_extras_asked_for_are_installed_once_beside_those_there(checkout: Path) -> None:
    assert bootstrap(checkout, "--extras", "demo") == ['.[demo]']
    assert (checkout / ".venv" / ".installed").read_text().split()[1] == "demo"
    assert bootstrap(checkout, "--extras", "demo") == []
    assert bootstrap(checkout) == ['.[all,test]']  # make test after make demo: the rest, "all" holding "demo"
    assert bootstrap(checkout, "--extras", "demo") == []  # make demo after make test: nothing
    assert bootstrap(checkout) == []
    assert bootstrap(checkout, "--extras", "test") == []


def test_a_changed_pyproject_installs_again_only_what_is_asked_for(checkout: Path) -> None:
    bootstrap(checkout, "--extras", "demo")
    with (checkout / "pyproject.toml").open("a") as file:
        file.write("\n# changed\n")
    assert bootstrap(checkout) == ['.[all,test]']


def test_an_empty_extras_list_is_refused_with_what_to_pass(checkout: Path) -> None:
    result = subprocess.run(["bash", "scripts/bootstrap.sh", "--extras", "", "no-packages.txt"], cwd=checkout,
                            capture_output=True, text=True)
    assert result.returncode != 0
    assert "--extras needs a comma-separated list of pyproject.toml's extras" in result.stderr
