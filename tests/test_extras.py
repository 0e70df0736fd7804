"""Optional dependencies (pyproject.toml's extras): the base install runs the daemon and the offline model
commands; a feature whose extra is missing says, in one line, which pip command brings it."""

from __future__ import annotations

import ast
import asyncio
import importlib.metadata
import re
import sys
import tomllib
from pathlib import Path

import pytest

import phantom
from phantom import MissingExtraError, PhantomError, require_extra

REPO = Path(__file__).resolve().parent.parent
PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())
EXTRAS: dict[str, list[str]] = PYPROJECT["project"]["optional-dependencies"]
#: The folders of the installed parts (tests/, bench/ and examples/ run with every extra installed).
PART_FOLDERS = ("phantom", "protocol", "model", "scan", "shape", "host", "hil", "design")


def canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def requirement(text: str) -> tuple[str, list[str]]:
    """``"dask[distributed]>=2024.1"`` -> ("dask", ["distributed"])."""
    match = re.match(r"\s*([A-Za-z0-9._-]+)\s*(?:\[([^\]]*)\])?", text)
    assert match, text
    return canonical(match.group(1)), [extra.strip() for extra in (match.group(2) or "").split(",") if extra.strip()]


def provided_by(requirements: list[str]) -> set[str]:
    """The distributions these requirements install: each one, and those its own extras pull in."""
    from packaging.requirements import Requirement

    names = set()
    for text in requirements:
        name, extras = requirement(text)
        names.add(name)
        for dependency in (importlib.metadata.requires(name) or []) if extras else []:
            parsed = Requirement(dependency)
            if parsed.marker and any(parsed.marker.evaluate({"extra": extra}) for extra in extras):
                names.add(canonical(parsed.name))
    return names


BASE = provided_by(PYPROJECT["project"]["dependencies"])
DISTRIBUTIONS = {module: {canonical(d) for d in dists}
                 for module, dists in importlib.metadata.packages_distributions().items()}


def optional_imports(path: Path) -> list[tuple[int, str, str | None]]:
    """(line, top-level module, extra or None) for each import of a third-party module outside the base install,
    with the extra of the ``with require_extra(...)`` block around it. Imports under ``if TYPE_CHECKING`` and in a
    ``try`` that handles ImportError (a probe with a fallback) are not imports of the running code."""
    found: list[tuple[int, str, str | None]] = []

    def visit(node: ast.AST, extra: str | None) -> None:
        if isinstance(node, ast.If) and isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING":
            return
        if isinstance(node, ast.Try) and any(
                isinstance(handler.type, ast.Name) and handler.type.id in ("ImportError", "ModuleNotFoundError")
                for handler in node.handlers):
            return
        if isinstance(node, ast.With):
            for item in node.items:
                call = item.context_expr
                if isinstance(call, ast.Call) and getattr(call.func, "id", getattr(call.func, "attr", None)) == \
                        "require_extra":
                    extra = ast.literal_eval(call.args[0])
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module]
        for name in names:
            top = name.partition(".")[0]
            if top in sys.stdlib_module_names or top == "phantom":
                continue
            if not DISTRIBUTIONS.get(top, {top}) & BASE:
                found.append((node.lineno, top, extra))
        for child in ast.iter_child_nodes(node):
            visit(child, extra)

    visit(ast.parse(path.read_text()), None)
    return found


def part_modules() -> list[Path]:
    return sorted(path for folder in PART_FOLDERS if (REPO / folder).is_dir() for path in (REPO / folder).rglob("*.py"))


def test_every_import_outside_the_base_install_names_the_extra_that_brings_it():
    wrong = []
    for path in part_modules():
        for line, module, extra in optional_imports(path):
            where = f"{path.relative_to(REPO)}:{line}: {module}"
            if extra is None:
                wrong.append(f"{where} is not in the base install: import it inside `with require_extra(EXTRA):`")
            elif extra not in EXTRAS:
                wrong.append(f"{where}: require_extra({extra!r}) names no extra of pyproject.toml")
            elif not DISTRIBUTIONS.get(module, {module}) & provided_by(EXTRAS[extra]):
                wrong.append(f"{where} does not come with the extra {extra!r} (pyproject.toml)")
    assert not wrong, "\n".join(wrong)


def test_the_checker_sees_an_unguarded_import(tmp_path):
    module = tmp_path / "m.py"
    module.write_text("import numpy\n\ndef f():\n    import trimesh\n    with require_extra('scan'):\n"
                      "        import pymeshfix\n    try:\n        import sksparse\n    except ImportError:\n"
                      "        pass\n")
    assert optional_imports(module) == [(4, "trimesh", None), (6, "pymeshfix", "scan")]


def test_all_holds_every_extra_but_test_and_flash_and_the_demo_s_share_of_them():
    _, named = requirement(EXTRAS["all"][0])
    assert set(named) == set(EXTRAS) - {"all", "test", "flash", "demo"}
    # scripts/bootstrap.sh installs nothing for `make demo` where "all" is installed: "all" must hold "demo"
    _, demo_named = requirement(EXTRAS["demo"][0])
    assert set(demo_named) < set(named)


def hide(monkeypatch, top: str) -> None:
    """Make ``import top`` (and its submodules) fail as if the package were not installed."""
    for name in [name for name in sys.modules if name == top or name.startswith(top + ".")]:
        monkeypatch.setitem(sys.modules, name, None)
    monkeypatch.setitem(sys.modules, top, None)


def check_message(error: pytest.ExceptionInfo, module: str, extra: str) -> None:
    message = str(error.value)
    assert isinstance(error.value, PhantomError)
    assert "\n" not in message
    assert message.startswith(f"{module} is not installed")
    assert message.endswith(f"pip install -e '{phantom.SOURCE_ROOT}[{extra}]'")


def test_require_extra_names_the_pip_command(monkeypatch):
    hide(monkeypatch, "trimesh")
    with pytest.raises(MissingExtraError) as error:
        with require_extra("scan"):
            import trimesh  # noqa: F401
    check_message(error, "trimesh", "scan")


def test_outside_a_checkout_the_command_names_the_distribution(monkeypatch):
    monkeypatch.setattr(phantom, "SOURCE_ROOT", None)
    assert phantom.install_command("record") == "pip install 'active-prostate-phantom[record]'"


def test_a_package_that_fails_to_load_is_reported_as_such():
    with pytest.raises(MissingExtraError, match=r"failed to import \(libfoo.so: cannot open\); reinstall"):
        with require_extra("scan"):
            raise ImportError("libfoo.so: cannot open")


def test_other_errors_pass_through():
    with pytest.raises(ValueError):
        with require_extra("scan"):
            raise ValueError("not an import")


def test_a_recording_without_rerun(monkeypatch, tmp_path):
    from phantom.host.recording import read_rrd

    hide(monkeypatch, "rerun")
    with pytest.raises(MissingExtraError) as error:
        read_rrd(tmp_path / "demo.rrd")
    check_message(error, "rerun", "record")


def test_a_can_bus_without_python_can(monkeypatch):
    from phantom.host.transports import CanTransport

    hide(monkeypatch, "can")
    with pytest.raises(MissingExtraError) as error:
        asyncio.run(CanTransport("phantom", interface="virtual").open())
    check_message(error, "can", "can")


def test_a_scan_without_trimesh(monkeypatch, tmp_path):
    from phantom.scan.compare import read_scan

    scan = tmp_path / "scan.ply"
    scan.write_text("ply\n")
    hide(monkeypatch, "trimesh")
    with pytest.raises(MissingExtraError) as error:
        read_scan(scan)
    check_message(error, "trimesh", "scan")


def test_a_sweep_without_dask(monkeypatch):
    from phantom.model.cluster import local_cluster

    hide(monkeypatch, "dask")
    with pytest.raises(MissingExtraError) as error:
        local_cluster(1)
    check_message(error, "dask", "calibrate")


def test_bench_plots_without_matplotlib(monkeypatch, tmp_path):
    from phantom.hil.bench import plot_steps

    hide(monkeypatch, "matplotlib")
    with pytest.raises(MissingExtraError) as error:
        plot_steps([], tmp_path / "steps.png")
    check_message(error, "matplotlib", "hil")


def test_cholmod_asked_for_without_scikit_sparse(monkeypatch):
    import scipy.sparse

    from phantom.model.fem.linsolve import Factorization, default_method

    hide(monkeypatch, "sksparse")
    assert default_method() == "splu-mmd"
    with pytest.raises(MissingExtraError) as error:
        Factorization(scipy.sparse.identity(3, format="csr"), method="cholmod")
    check_message(error, "sksparse", "cholmod")
