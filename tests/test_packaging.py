"""The package a user installs: ``python -m build`` makes a wheel that installs into a fresh virtual environment
and runs outside the repository, with an empty cache, so the firmware's sources, the simavr harness and the
scenes must come from the wheel (its package data), not from the checkout."""

import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import pytest

import phantom

REPO = Path(__file__).resolve().parent.parent

pytestmark = [pytest.mark.slow, pytest.mark.sim, pytest.mark.timeout(900)]


def run(command: list[str], cwd: Path, env: dict[str, str] | None = None) -> str:
    result = subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, f"{' '.join(command)}:\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
    return result.stdout


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> dict[str, Path]:
    """The wheel, built from the checkout, installed into a fresh venv (its dependencies from pip's index)."""
    root = tmp_path_factory.mktemp("packaging")
    run([sys.executable, "-m", "build", "--wheel", "--outdir", str(root / "dist"), str(REPO)], cwd=root)
    wheel = next((root / "dist").glob("*.whl"))
    venv.create(root / "venv", with_pip=True)
    run([str(root / "venv" / "bin" / "python"), "-m", "pip", "install", "--quiet", str(wheel)], cwd=root)
    return {"root": root, "wheel": wheel, "phantom": root / "venv" / "bin" / "phantom"}


def user_env(root: Path) -> dict[str, str]:
    """A user's environment: an empty cache of its own, no PYTHONPATH into the checkout."""
    return {"PATH": f"{root / 'venv' / 'bin'}:/usr/bin:/bin", "HOME": str(root), "LANG": "C.UTF-8",
            "PHANTOM_CACHE_DIR": str(root / "cache")}


def test_the_wheel_carries_the_firmware_sources_the_harness_and_the_scenes(installed):
    names = set(zipfile.ZipFile(installed["wheel"]).namelist())
    expected = {"phantom/hil/firmware_sources/Makefile", "phantom/hil/firmware_sources/src/phantom.ino",
                "phantom/hil/firmware_sources/src/core/controller.cpp", "phantom/hil/harness/main.c",
                "phantom/hil/harness/Makefile", "phantom/model/scenes/prostate_calibrated.toml",
                "phantom/model/scenes/prostate_converged.volumes.npz",
                "phantom/model/scenes/prostate_converged.shapes.npz",
                "phantom/host/scenes/bph_growth.toml", "phantom/protocol/spec.toml"}
    assert expected <= names, sorted(expected - names)
    assert not any("/build/" in name or name.endswith((".o", ".elf", ".hex")) for name in names)


def test_the_installed_example_scenes_find_the_table_files_they_name(installed):
    # (the host's scenes name the model's shipped table files by a path relative to themselves)
    root = installed["root"]
    output = run([str(root / "venv" / "bin" / "python"), "-c",
                  "from phantom.host.scenes import example_scene_path\n"
                  "from phantom.host.scenes import load_timeline_scene\n"
                  "settings = load_timeline_scene(example_scene_path('bph_growth')).model_settings\n"
                  "print(settings.table_volumes.is_file(), settings.table_shapes.is_file(), settings.table_shapes)"],
                 cwd=root, env=user_env(root))
    assert output.split()[:2] == ["True", "True"] and "site-packages/phantom/model/scenes" in output, output


def test_the_installed_package_solves_a_forward_case_outside_the_repository(installed):
    root = installed["root"]
    output = run([str(installed["phantom"]), "forward", "--scene", "builtin", "--pressures-kpa", "1,1,1"],
                 cwd=root, env=user_env(root))
    gland = next(line for line in output.splitlines() if line.startswith("gland")).split()
    assert 20.0 < float(gland[1]) < float(gland[2]) < 40.0, output  # rest volume, then the inflated one


def test_the_installed_package_builds_the_firmware_and_shakes_hands_with_the_simulated_board(installed):
    root = installed["root"]
    output = run([str(installed["phantom"]), "hil", "handshake", "--sim"], cwd=root, env=user_env(root))
    assert "passed: True" in output and "firmware_version:" in output, output
    assert (root / "cache" / "firmware" / "uno-bench" / "phantom.elf").is_file(), "built into the user's cache"


def test_the_installed_package_says_its_version(installed):
    root = installed["root"]
    output = run([str(installed["phantom"]), "--version"], cwd=root, env=user_env(root))
    assert output.split() == ["phantom", phantom.__version__]
