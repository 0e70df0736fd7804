"""Regenerate every image the docs show, with the project's own commands, and print what was written.

    make figures                                   # all of them (tens of minutes: the bench plots solve a lot)
    .venv/bin/python scripts/figures.py --only docs/img/hil_steps_sim.png docs/img/compare_scan_heatmap.png
    .venv/bin/python scripts/figures.py --list     # the images and the commands that make them

Each figure is one or more command lines run from the repository root (the caption beside the image in the docs
names the same command and scene); intermediate files go to out/figures/ (git ignores out/). The Rerun
screenshots need Debian's chromium (scripts/apt-packages-figures.txt; `make figures` installs it).
"""

from __future__ import annotations

import argparse
import shutil
import struct
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
WORK = Path("out/figures")
PYTHON = str(Path(sys.executable))
PHANTOM = str(Path(sys.executable).with_name("phantom"))


@dataclass(frozen=True)
class Figure:
    """An image the docs show: where it goes, what it shows, the commands that make it, and where the last
    command writes it (None: at ``path`` itself)."""

    path: str
    shows: str
    commands: tuple[tuple[str, ...], ...]
    product: str | None = None


FIGURES = (
    Figure("docs/img/rerun_view.png",
           "Rerun's web viewer on a 90 s recording of gland-volume steps made from the calibrated model",
           ((PYTHON, "bench/recording_view.py", "--out", f"{WORK}/recording_view.rrd",
             "--screenshot", "docs/img/rerun_view.png"),)),
    Figure("docs/img/rerun_demo.png",
           "make demo's recording (the daemon on the simulated board, BPH growth scene) in Rerun's web viewer",
           (("make", "demo"),
            (PYTHON, "bench/recording_view.py", "--rrd", "out/demo.rrd", "--screenshot", "docs/img/rerun_demo.png"))),
    Figure("docs/img/panel.png",
           "the browser panel (phantom daemon --sim --http) after its symmetric BPH preset was reached",
           ((PYTHON, "scripts/panel_screenshot.py", "--out", "docs/img/panel.png"),)),
    Figure("docs/img/hil_steps_sim.png",
           "the HIL report's step responses on the simulated board (firmware in simavr, hil/plant.toml)",
           ((PHANTOM, "hil", "report", "--sim", "--out", f"{WORK}/hil-report"),),
           product=f"{WORK}/hil-report/steps.png"),
    Figure("docs/img/compare_scan_heatmap.png",
           "compare-scan of a synthetic scan (15 % softer material) against builtin:calibrated at 1, 2, 0.5 kPa",
           ((PHANTOM, "scan", "synthetic", "--out", f"{WORK}/softer_scan.ply", "--modulus-factor", "0.85"),
            (PHANTOM, "compare-scan", f"{WORK}/softer_scan.ply", "--scene", "builtin:calibrated",
             "--pressures-kpa", "1,2,0.5", "--out", str(WORK))),
           product=f"{WORK}/softer_scan_vs_model.png"),
    Figure("bench/shape_average_vs_model.png",
           "the shape analysis on 120 synthetic prostates: the model's rest shape against the decoded average (Fig. 5)",
           ((PHANTOM, "shape", "synthesize", "--out", f"{WORK}/shape-data", "--cases", "120", "--seed", "0"),
            (PHANTOM, "shape", "train", f"{WORK}/shape-data", "--out", f"{WORK}/shape-run", "--epochs", "100",
             "--replace"),
            (PHANTOM, "shape", "report", f"{WORK}/shape-run", "--out", f"{WORK}/shape-report")),
           product=f"{WORK}/shape-report/average_vs_model.png"),
    Figure("bench/shape_cluster_1_vs_2.png",
           "the shape analysis's clusters 1 and 2 as an implicit-distance heatmap (Fig. 6), from the run above",
           ((PHANTOM, "shape", "report", f"{WORK}/shape-run", "--out", f"{WORK}/shape-report"),),
           product=f"{WORK}/shape-report/cluster_1_vs_2.png"),
    Figure("bench/shape_loss.png",
           "the shape VAE's loss curves and held-out IoU, from the run above",
           ((PHANTOM, "shape", "report", f"{WORK}/shape-run", "--out", f"{WORK}/shape-report"),),
           product=f"{WORK}/shape-report/loss.png"),
    Figure("bench/response_table.png",
           "the calibrated scene's response table against full solves along (p, 0, 0) and (p, p, p)",
           ((PYTHON, "bench/response_table.py", "--plot", "bench/response_table.png"),)),
    Figure("bench/model_fidelity.png",
           "run time against error of the fidelity levels and mesh sizes, built-in scene and the Lame sphere",
           ((PYTHON, "bench/model_fidelity.py", "--sizes-mm", "6,5,4,3", "--reference-mm", "2.5",
             "--sphere-sizes-mm", "6,4,3,2.5", "--inverse-mm", "3", "--out", "bench/model_fidelity.png"),)),
    Figure("bench/model_ladder.png",
           "the prostate's fidelity ladder: time per answer against error from the converged growth, 4- and 10-node",
           ((PYTHON, "bench/model_convergence.py", "--linear-sizes-mm", "4,3,2.5", "--quadratic-sizes-mm", "10,7,5,4",
             "--youngs-modulus-kpa", "50", "--poisson-ratio", "0.4996", "--plot", "bench/model_ladder.png"),)),
    Figure("bench/scan_accuracy.png",
           "the scanner's volume error and mean distance on the simulated rig against views and picture size",
           ((PYTHON, "bench/scan_accuracy.py", "--out", "bench"),)),
    Figure("bench/scan_concavity.png",
           "a cut through a dented sphere and its visual hull (what the silhouettes cannot show)",
           ((PYTHON, "bench/scan_accuracy.py", "--concavity-only", "--out", "bench"),)),
)


def png_size(path: Path) -> tuple[int, int]:
    """Width and height of a PNG, from its header."""
    header = path.read_bytes()[:24]
    if header[:8] != b"\x89PNG\r\n\x1a\n":
        raise ValueError(f"{path} is not a PNG")
    width, height = struct.unpack(">II", header[16:24])
    return width, height


def shown(command: tuple[str, ...]) -> str:
    """A command as a person would type it (the venv's python and phantom by their short names)."""
    names = {PYTHON: ".venv/bin/python", PHANTOM: "phantom"}
    return " ".join(names.get(word, word) for word in command)


def make(figure: Figure) -> float:
    """Run the figure's commands and put the image in place; returns the seconds it took."""
    started = time.perf_counter()
    (REPO / WORK).mkdir(parents=True, exist_ok=True)
    for command in figure.commands:
        print(f"  $ {shown(command)}", flush=True)
        subprocess.run(command, cwd=REPO, check=True)
    if figure.product is not None:
        shutil.copyfile(REPO / figure.product, REPO / figure.path)
    return time.perf_counter() - started


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="+", metavar="PATH", help="make only these images (paths as listed)")
    parser.add_argument("--list", action="store_true", help="list the images and their commands, make nothing")
    args = parser.parse_args(argv)
    known = {figure.path: figure for figure in FIGURES}
    unknown = sorted(set(args.only or ()) - set(known))
    if unknown:
        parser.error(f"no such figure: {', '.join(unknown)}; --list shows them")
    chosen = [known[path] for path in args.only] if args.only else list(FIGURES)
    if args.list:
        for figure in chosen:
            print(f"{figure.path}: {figure.shows}")
            for command in figure.commands:
                print(f"  $ {shown(command)}")
        return 0
    written = []
    for figure in chosen:
        print(f"{figure.path}: {figure.shows}", flush=True)
        seconds = make(figure)
        width, height = png_size(REPO / figure.path)
        size_kb = (REPO / figure.path).stat().st_size / 1e3
        written.append(f"wrote {figure.path} ({width}x{height}, {size_kb:.0f} KB) in {seconds:.0f} s")
        print(written[-1], flush=True)
    print("\n".join(["", *written]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
