"""Every ``phantom ...`` command line shown in the READMEs works.

The lines are read from the READMEs' code blocks at test time, so that a line added later (by any part) is
tested too. Each is parsed by the real ``phantom`` parser (a renamed flag, or a value argparse mistakes for an
option, fails here). The daemon's clients (status, set, vent, zero, clear-fault, run-scene, watch) and the
offline inverse also run: the clients against a daemon started with its defaults on the simulated board (so
the shipped example scenes must be accepted by it), the inverse on the calibrated scene. A line "works" when it
exits 0 (a README line refused with its documented arguments does not work), or is one of ``REFUSED_ON_PURPOSE``
and exits 2 with that one-line error; never with a usage error or a traceback. The rest (the daemon itself, the
bench, the model's long computations) is parsed only: a dry run.

Runtime shortcuts, stated here: ``watch`` without ``--count`` gets ``--count 2``; ``run-scene --time-scale X``
plays at 60 (the timelines last minutes).
"""

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
from daemon_rig import daemon_process

from phantom.cli.main import build_parser, join_list_values

ROOT = Path(__file__).resolve().parent.parent
PHANTOM = Path(sys.executable).with_name("phantom")
#: Subcommands that talk to a running daemon.
CLIENTS = {"status", "set", "vent", "zero", "clear-fault", "run-scene", "watch"}
#: Offline subcommands fast enough to run.
RUN_OFFLINE = {"inverse"}
#: The README lines that may be refused where they run here, each with the one-line error that says why (the
#: README's own words for when it is); any other exit but 0 fails.
REFUSED_ON_PURPOSE = {
    # run just after the README's `phantom vent`: host/README.md says zero wants the readings vented and steady
    "phantom zero": "the board refused to zero its sensors: NOT_SETTLED (the readings are not steady yet",
}


def readme_command_lines() -> list[tuple[str, str]]:
    """(where, command line) for every ``phantom SUBCOMMAND ...`` line of the READMEs' code blocks."""
    found = []
    for readme in sorted(ROOT.glob("**/README.md")):
        if any(part.startswith(".") or part in ("node_modules", "build") for part in readme.relative_to(ROOT).parts):
            continue
        lines = readme.read_text().splitlines()
        in_fence = False
        index = 0
        while index < len(lines):
            line = lines[index]
            if line.strip().startswith("```"):
                in_fence = not in_fence
            code = in_fence or line.startswith("    ")
            text = line.strip().removeprefix("$ ")
            while text.endswith("\\") and index + 1 < len(lines):
                index += 1
                text = text[:-1] + " " + lines[index].strip()
            # a subcommand, not a log line such as "phantom daemon: ready"
            if code and re.match(r"phantom [a-z][a-z-]*( |$)", text):
                # the phantom command alone: without its comment, or what a shell pipes or chains after it
                command = re.split(r" #| \| | && | ; | > ", text)[0].strip()
                found.append((f"{readme.relative_to(ROOT)}:{index + 1}", command))
            index += 1
    return found


def variants(line: str) -> list[list[str]]:
    """The argument lists a line stands for: without its [optional parts], and with those that hold no
    placeholder (an upper-case metavar like H or FILE)."""
    optional = re.findall(r"\[([^\]]*)\]", line)
    bare = shlex.split(re.sub(r"\s*\[[^\]]*\]", "", line))[1:]
    forms = [bare]
    concrete = [part for part in optional if not any(re.fullmatch(r"[A-Z][A-Z_]*", word) for word in part.split())]
    if concrete:
        forms.append(bare + shlex.split(" ".join(concrete)))
    return forms


LINES = readme_command_lines()


def test_the_readmes_show_command_lines_of_the_host():
    subcommands = {shlex.split(line)[1] for _, line in LINES}
    assert {"daemon", "status", "set", "vent", "zero", "run-scene", "watch", "sim-board"} <= subcommands


@pytest.mark.parametrize(("where", "line"), LINES, ids=[where for where, _ in LINES])
def test_every_readme_command_line_parses(where, line):
    parser = build_parser()
    for arguments in variants(line):
        try:
            parser.parse_args(join_list_values(arguments))
        except SystemExit as error:
            pytest.fail(f"{where}: `{line}` does not parse (exit {error.code})")


@pytest.fixture(scope="module")
def default_daemon(tmp_path_factory, default_model_cached):
    """``phantom daemon --sim`` with every default (scene builtin:converged), at twice real time."""
    with daemon_process(tmp_path_factory.mktemp("readme"), "--sim", "--sim-speed", "2", ready_s=90) as daemon:
        yield daemon.socket


CLIENT_LINES = [(where, line) for where, line in LINES if shlex.split(line)[1] in CLIENTS]
OFFLINE_LINES = [(where, line) for where, line in LINES if shlex.split(line)[1] in RUN_OFFLINE]


@pytest.mark.sim
@pytest.mark.slow
@pytest.mark.parametrize(("where", "line"), CLIENT_LINES, ids=[where for where, _ in CLIENT_LINES])
def test_every_readme_client_line_runs(default_daemon, where, line):
    runs(where, line, {**os.environ, "PHANTOM_SOCKET": str(default_daemon)})


# the offline lines need no daemon: they are not marked sim, so make check runs them and make test runs them at a
# lower priority beside the simavr tests
@pytest.mark.slow
@pytest.mark.parametrize(("where", "line"), OFFLINE_LINES, ids=[where for where, _ in OFFLINE_LINES])
def test_every_readme_inverse_line_runs(where, line, tmp_path):
    from test_shape_inverse import lopsided_mask

    # the patient's mask the README names is the reader's own: here, a gland with its left lobe enlarged
    inputs = {"patient_mask.nii.gz": str(lopsided_mask(tmp_path / "patient_mask.nii.gz"))}
    runs(where, line, dict(os.environ), inputs)


def runs(where: str, line: str, environment: dict[str, str], inputs: dict[str, str] | None = None) -> None:
    """Run each variant of a README line, the input files it names replaced by ``inputs`` (name -> path): it exits
    0 (or is refused on purpose, with its error); a client prints something."""
    for arguments in variants(line):
        arguments = [(inputs or {}).get(argument, argument) for argument in arguments]
        if arguments[0] == "watch" and "--count" not in arguments:
            arguments = [*arguments, "--count", "2"]
        if arguments[0] == "run-scene" and "--time-scale" in arguments:
            position = arguments.index("--time-scale")
            arguments = [*arguments[:position + 1], "60", *arguments[position + 2:]]
        result = subprocess.run([str(PHANTOM), *arguments], capture_output=True, text=True, timeout=120, cwd=ROOT,
                                env=environment)
        assert "Traceback" not in result.stderr and "usage:" not in result.stderr, f"{where}: {result.stderr}"
        errors = [text for text in result.stderr.splitlines() if ": error: " in text]
        refusal = REFUSED_ON_PURPOSE.get(line)
        assert result.returncode == 0 or (refusal is not None and result.returncode == 2 and len(errors) == 1
                                          and refusal in errors[0]), (
            f"{where}: `phantom {' '.join(arguments)}` exited {result.returncode}: {result.stderr}")
        if arguments[0] in CLIENTS and result.returncode == 0:
            assert result.stdout.strip() or arguments[0] == "run-scene", f"{where}: no output"
