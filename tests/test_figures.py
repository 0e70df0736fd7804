"""`make figures` (scripts/figures.py) makes every image the docs show, with commands that exist."""

import functools
import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import pytest

from phantom.cli.main import build_parser

REPO = Path(__file__).resolve().parent.parent
IMAGE = re.compile(r"!\[[^\]]*\]\(([^)\s]+\.png)\)")


@functools.cache
def figures_module():
    """scripts/figures.py as a module (registered first: its dataclass looks its module up)."""
    spec = importlib.util.spec_from_file_location("figures_script", REPO / "scripts" / "figures.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def tracked(pattern: str) -> list[Path]:
    listed = subprocess.run(["git", "ls-files", pattern], cwd=REPO, capture_output=True, text=True, check=True)
    return [REPO / name for name in listed.stdout.split()]


def shown_images() -> set[str]:
    """Every PNG a tracked Markdown file embeds, as a path from the repository root."""
    images = set()
    for document in tracked("*.md"):
        for target in IMAGE.findall(document.read_text()):
            images.add((document.parent / target).resolve().relative_to(REPO).as_posix())
    return images


def test_the_figures_are_the_images_the_docs_show_and_the_repository_holds():
    made = {figure.path for figure in figures_module().FIGURES}
    committed = {path.relative_to(REPO).as_posix() for path in tracked("*.png")}
    assert shown_images() <= made, "an image the docs show that scripts/figures.py does not make"
    assert committed == made, "the PNGs in git and those scripts/figures.py makes differ"


def test_each_figure_command_exists():
    module = figures_module()
    parser = build_parser()
    for figure in module.FIGURES:
        for command in figure.commands:
            if command[0] == module.PHANTOM:
                parser.parse_args(list(command[1:]))
            elif command[0] == module.PYTHON:
                assert (REPO / command[1]).is_file(), command
            else:
                assert command[:2] == ("make", "demo"), command


def test_the_list_names_each_figure_and_its_commands(capsys):
    module = figures_module()
    assert module.main(["--list", "--only", "docs/img/hil_steps_sim.png"]) == 0
    assert capsys.readouterr().out.splitlines() == [
        "docs/img/hil_steps_sim.png: the HIL report's step responses on the simulated board (firmware in simavr, "
        "hil/plant.toml)",
        "  $ phantom hil report --sim --out out/figures/hil-report"]


def test_an_unknown_figure_is_refused(capsys):
    with pytest.raises(SystemExit) as exit_:
        figures_module().main(["--only", "nope.png"])
    assert exit_.value.code == 2
    assert "no such figure: nope.png" in capsys.readouterr().err


def test_png_size_reads_the_header(tmp_path):
    module = figures_module()
    assert module.png_size(REPO / "docs" / "img" / "hil_steps_sim.png")[0] > 100
    (tmp_path / "x.png").write_bytes(b"GIF89a" + bytes(30))
    with pytest.raises(ValueError, match="not a PNG"):
        module.png_size(tmp_path / "x.png")
