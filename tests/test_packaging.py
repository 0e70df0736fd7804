"""The package a user installs: ``python -m build`` makes a wheel that installs into a fresh virtual environment
and runs outside the repository, with an empty cache, so the firmware's sources, the simavr harness and the
scenes must come from the wheel (its package data), not from the checkout.

Building the wheel and its venv takes minutes of CPU and no simulated board: it is done once for each state of
the checkout (:func:`checkout_key`) and kept in the cache, so that whichever of make test's two pytest runs asks
first builds it and the other (the ``sim`` run, where only the handshake with the simulated board runs) finds it
built."""

import hashlib
import os
import re
import shutil
import subprocess
import sys
import tomllib
import venv
import zipfile
from pathlib import Path

import pytest
from conftest import machine_lock

import phantom

REPO = Path(__file__).resolve().parent.parent
#: How many installed checkouts the cache keeps (half a gigabyte each): the others are removed when one is built.
KEPT_INSTALLS = 2

pytestmark = [pytest.mark.slow, pytest.mark.timeout(900)]


def run(command: list[str], cwd: Path, env: dict[str, str] | None = None) -> str:
    result = subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, f"{' '.join(command)}:\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
    return result.stdout


def checkout_key() -> str | None:
    """A hash of the files the wheel is built from as they are now in the checkout (pyproject.toml, the README
    and the folders its package-dir maps; tracked with their changes, and untracked ones .gitignore does not
    exclude), None outside a git checkout: the same key is the same wheel."""
    config = tomllib.loads((REPO / "pyproject.toml").read_text())
    sources = ["pyproject.toml", "README.md", "LICENSE", *config["tool"]["setuptools"]["package-dir"].values()]

    def git(*arguments: str) -> bytes:
        return subprocess.run(["git", *arguments, "--", *sources], cwd=REPO, capture_output=True, check=True,
                              timeout=60).stdout
    try:
        digest = hashlib.sha256(git("ls-files", "--stage") + git("diff", "HEAD", "--binary"))
        for name in sorted(git("ls-files", "--others", "--exclude-standard", "-z").split(b"\0")):
            if name and (REPO / name.decode()).is_file():
                digest.update(name + b"\0" + (REPO / name.decode()).read_bytes())
    except (OSError, subprocess.SubprocessError):
        return None
    return digest.hexdigest()[:16]


def build_and_install(root: Path) -> None:
    """The wheel built from the checkout into ``root/dist``, installed into a fresh venv ``root/venv`` (its
    dependencies from pip's index)."""
    run([sys.executable, "-m", "build", "--wheel", "--outdir", str(root / "dist"), str(REPO)], cwd=root)
    venv.create(root / "venv", with_pip=True)
    # --no-compile: as scripts/bootstrap.sh installs (pip's byte-compiling is a third of an install's time); the
    # few modules a command imports compile on first use
    run([str(root / "venv" / "bin" / "python"), "-m", "pip", "install", "--quiet", "--no-compile",
         str(next((root / "dist").glob("*.whl")))], cwd=root)


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> dict[str, Path]:
    """The wheel, built from the checkout, installed into a fresh venv: built once for this state of the checkout
    (the other pytest workers and make test's other pytest run wait for it and reuse it), or in a temporary folder
    outside a git checkout. The tests write nothing into its venv but Python's bytecode caches: each gets its own
    empty cache."""
    key = checkout_key()
    if key is None:
        root = tmp_path_factory.mktemp("packaging")
        build_and_install(root)
    else:
        installs = phantom.cache_dir("test-packaging")
        root = installs / key
        with machine_lock("test-packaging"):
            if (root / "installed").is_file():
                os.utime(root)  # the most recently used installs are the ones kept
            else:
                shutil.rmtree(root, ignore_errors=True)
                root.mkdir()
                build_and_install(root)
                (root / "installed").write_text(key)
                older = sorted((path for path in installs.iterdir() if path != root), key=lambda p: p.stat().st_mtime)
                for path in older[:max(0, len(older) - (KEPT_INSTALLS - 1))]:
                    shutil.rmtree(path, ignore_errors=True)
    return {"root": root, "wheel": next((root / "dist").glob("*.whl")), "phantom": root / "venv" / "bin" / "phantom"}


def user_env(installed: dict[str, Path], home: Path) -> dict[str, str]:
    """A user's environment: the installed venv on PATH, a home and an empty cache of its own (under ``home``), no
    PYTHONPATH into the checkout."""
    return {"PATH": f"{installed['root'] / 'venv' / 'bin'}:/usr/bin:/bin", "HOME": str(home), "LANG": "C.UTF-8",
            "PHANTOM_CACHE_DIR": str(home / "cache")}


def test_the_wheel_carries_the_firmware_sources_the_harness_and_the_scenes(installed):
    names = set(zipfile.ZipFile(installed["wheel"]).namelist())
    expected = {"phantom/hil/firmware_sources/Makefile", "phantom/hil/firmware_sources/src/phantom.ino",
                "phantom/hil/firmware_sources/src/core/controller.cpp", "phantom/hil/harness/main.c",
                "phantom/hil/harness/Makefile", "phantom/model/scenes/prostate_calibrated.toml",
                "phantom/model/scenes/prostate_calibrated.volumes.npz",
                "phantom/model/scenes/prostate_calibrated.shapes.npz",
                "phantom/model/scenes/prostate_converged.volumes.npz",
                "phantom/model/scenes/prostate_converged.shapes.npz",
                "phantom/host/scenes/bph_growth.toml", "phantom/protocol/spec.toml",
                # the browser panel's page and its vendored libraries (phantom daemon --http serves them)
                "phantom/host/panel/index.html", "phantom/host/panel/panel.js",
                "phantom/host/panel/vendor/three/three.module.min.js", "phantom/host/panel/vendor/uplot/LICENSE"}
    assert expected <= names, sorted(expected - names)
    assert not any("/build/" in name or name.endswith((".o", ".elf", ".hex")) for name in names)


def test_the_installed_example_scenes_find_the_table_files_they_name(installed, tmp_path):
    # (the host's scenes name the model's shipped table files by a path relative to themselves)
    output = run([str(installed["root"] / "venv" / "bin" / "python"), "-c",
                  "from phantom.host.scenes import example_scene_path\n"
                  "from phantom.host.scenes import load_timeline_scene\n"
                  "settings = load_timeline_scene(example_scene_path('bph_growth')).model_settings\n"
                  "print(settings.table_volumes.is_file(), settings.table_shapes.is_file(), settings.table_shapes)"],
                 cwd=tmp_path, env=user_env(installed, tmp_path))
    assert output.split()[:2] == ["True", "True"] and "site-packages/phantom/model/scenes" in output, output


def test_the_installed_package_solves_a_forward_case_outside_the_repository(installed, tmp_path):
    output = run([str(installed["phantom"]), "forward", "--scene", "builtin", "--pressures-kpa", "1,1,1"],
                 cwd=tmp_path, env=user_env(installed, tmp_path))
    gland = next(line for line in output.splitlines() if line.startswith("gland")).split()
    assert 20.0 < float(gland[1]) < float(gland[2]) < 40.0, output  # rest volume, then the inflated one


def test_the_installed_package_is_the_base_install_whose_missing_extra_is_named(installed, tmp_path):
    """The wheel installed without an extra (what ``pip install active-prostate-phantom`` gives) holds none of the
    extras' packages, imports the daemon, and refuses a scan comparison in one line naming the pip command that
    brings its extra (the distribution's: outside a checkout). (The forward solve above is the base install's
    model; this venv is the one base install make test builds.)"""
    config = tomllib.loads((REPO / "pyproject.toml").read_text())
    python, env = str(installed["root"] / "venv" / "bin" / "python"), user_env(installed, tmp_path)
    listed = run([python, "-m", "pip", "list", "--format=freeze"], cwd=tmp_path, env=env)
    names = {re.sub(r"[-_.]+", "-", line.partition("==")[0]).lower() for line in listed.splitlines()}
    for extra in ("record", "can", "scan", "calibrate", "cholmod"):
        wanted = {re.sub(r"[-_.]+", "-", re.split(r"[\s\[<>=!~;]", text, maxsplit=1)[0]).lower()
                  for text in config["project"]["optional-dependencies"][extra]}
        assert not names & wanted, (extra, names & wanted)
    run([python, "-c", "import phantom.host.daemon, phantom.cli.daemon"], cwd=tmp_path, env=env)
    scan = tmp_path / "scan.ply"
    scan.write_text("ply\n")
    refused = subprocess.run([str(installed["phantom"]), "compare-scan", str(scan), "--scene", "builtin",
                              "--pressures-kpa", "0,0,0"], cwd=tmp_path, env=env, capture_output=True, text=True,
                             timeout=120)
    assert refused.returncode == 2 and refused.stderr.strip().count("\n") == 0, refused.stderr
    assert "pip install 'active-prostate-phantom[scan]'" in refused.stderr, refused.stderr


@pytest.mark.sim
def test_the_installed_package_builds_the_firmware_and_shakes_hands_with_the_simulated_board(installed, tmp_path):
    output = run([str(installed["phantom"]), "hil", "handshake", "--sim"], cwd=tmp_path,
                 env=user_env(installed, tmp_path))
    assert "passed: True" in output and "firmware_version:" in output, output
    assert (tmp_path / "cache" / "firmware" / "uno-bench" / "phantom.elf").is_file(), "built into the user's cache"


def test_the_installed_package_says_its_version(installed, tmp_path):
    output = run([str(installed["phantom"]), "--version"], cwd=tmp_path, env=user_env(installed, tmp_path))
    assert output.split() == ["phantom", phantom.__version__]
