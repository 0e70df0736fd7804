"""The import contract between the parts (docs/architecture.md, "The parts and their boundaries").

Each top-level folder is one part, mapped to a subpackage of ``phantom`` in pyproject.toml's
``[tool.setuptools.package-dir]``; ``phantom/cli`` (and ``phantom/__main__.py``) is the part that joins the others,
and the root ``phantom/__init__.py`` may be imported by all. import-linter cannot see this layout (folders mapped
into one package), so the modules are read here with ``ast``: every ``import`` and ``from ... import`` counts,
at module level, inside a function or under ``TYPE_CHECKING``, and so does a string that names one of our modules
exactly (``importlib.import_module("phantom.hil.sim")``, a table of lazy exports).
"""

from __future__ import annotations

import ast
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent

ROOT = "root"
CLI = "cli"

#: Which parts each part may import, besides itself. The CLI may import every part.
ALLOWED: dict[str, frozenset[str]] = {
    ROOT: frozenset(),
    "protocol": frozenset({ROOT}),
    "model": frozenset({ROOT, "protocol"}),
    "scan": frozenset({ROOT, "protocol", "model"}),
    "shape": frozenset({ROOT, "protocol", "model"}),
    "host": frozenset({ROOT, "protocol", "model"}),
    "hil": frozenset({ROOT, "protocol", "model"}),
    "design": frozenset({ROOT, "protocol", "model", "shape"}),
}

#: The one thing the root hands out from a part: ``phantom.connect()`` gives the host's client (the Python API of
#: the running daemon), imported when a script connects, so that every part's import of the root stays light.
ROOT_FACADE = frozenset({"phantom.host.client", "phantom.host.client.connect", "phantom.host.client.connect_async",
                         "phantom.host.client.Phantom", "phantom.host.client.AsyncPhantom"})

#: A string constant that is exactly a dotted name of one of our modules.
MODULE_NAME = re.compile(r"phantom(\.[A-Za-z_][A-Za-z0-9_]*)+")


@dataclass(frozen=True)
class Violation:
    path: str
    line: int
    part: str
    target: str
    target_part: str

    def __str__(self) -> str:
        return f"{self.path}:{self.line}: {self.part} imports {self.target} ({self.target_part})"


def part_folders(repo: Path) -> dict[str, Path]:
    """Each part's folder, from pyproject.toml's package-dir (``"phantom.host" = "host"`` -> host: repo/host)."""
    config = tomllib.loads((repo / "pyproject.toml").read_text())
    package_dirs: dict[str, str] = config["tool"]["setuptools"]["package-dir"]
    folders = {package.split(".")[1]: repo / folder for package, folder in package_dirs.items()
               if package.count(".") == 1}
    folders[CLI] = repo / package_dirs["phantom"] / "cli"
    return folders


def modules(repo: Path) -> list[tuple[str, str, Path]]:
    """Every Python module of every part: (part, dotted module name, path)."""
    found = []
    root_folder = repo / "phantom"
    found.append((ROOT, "phantom", root_folder / "__init__.py"))
    if (root_folder / "__main__.py").is_file():
        found.append((CLI, "phantom.__main__", root_folder / "__main__.py"))
    for part, folder in part_folders(repo).items():
        package = "phantom.cli" if part == CLI else f"phantom.{part}"
        for path in sorted(folder.rglob("*.py")):
            relative = path.relative_to(folder).with_suffix("")
            names = [name for name in relative.parts if name != "__init__"]
            found.append((part, ".".join([package, *names]), path))
    return found


def imported_names(tree: ast.Module, module: str, is_package: bool) -> list[tuple[int, str]]:
    """(line, dotted name) of everything ``module`` imports, anywhere in its code; ``from a import b`` gives
    ``a.b`` (b may be a module)."""
    names = []
    package = module if is_package else module.rpartition(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[:len(anchor) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            names += [(node.lineno, f"{base}.{alias.name}") for alias in node.names]
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and MODULE_NAME.fullmatch(node.value):
            names.append((node.lineno, node.value))
    return names


def part_of(name: str, parts: set[str]) -> str | None:
    """The part a dotted name belongs to: ``phantom.host.daemon`` -> host, ``phantom.PhantomError`` -> root,
    anything outside ``phantom`` -> None."""
    head, _, rest = name.partition(".")
    if head != "phantom":
        return None
    sub = rest.partition(".")[0]
    if sub in parts:
        return sub
    if sub == "__main__":
        return CLI
    return ROOT


def violations(repo: Path) -> tuple[list[Violation], list[tuple[str, str]]]:
    """Imports that break :data:`ALLOWED`, and the parts that have no rule yet."""
    found = modules(repo)
    parts = {part for part, _, _ in found} - {ROOT}
    unknown = [(part, "has no rule in ALLOWED: add one (and to docs/architecture.md)")
               for part in sorted(parts) if part != CLI and part not in ALLOWED]
    broken = []
    for part, module, path in found:
        if part == CLI:
            continue
        tree = ast.parse(path.read_text(), filename=str(path))
        for line, name in imported_names(tree, module, path.name == "__init__.py"):
            target = part_of(name, parts)
            if target is None or target == part or target in ALLOWED.get(part, frozenset()):
                continue
            if part == ROOT and name in ROOT_FACADE:
                continue
            broken.append(Violation(path.relative_to(repo).as_posix(), line, part, name, target))
    return broken, unknown


def test_every_part_imports_only_what_the_contract_allows():
    broken, unknown = violations(REPO)
    assert not unknown, unknown
    assert not broken, "imports across the parts' boundaries (docs/architecture.md):\n" + "\n".join(map(str, broken))


def test_the_checker_reads_every_part():
    found = modules(REPO)
    per_part: dict[str, int] = {}
    for part, _, _ in found:
        per_part[part] = per_part.get(part, 0) + 1
    assert {ROOT, CLI, "protocol", "model", "scan", "host", "hil"} <= set(per_part)
    assert all(count >= 1 for count in per_part.values())
    on_disk = {p for folder in ("protocol", "model", "scan", "host", "hil") for p in (REPO / folder).rglob("*.py")}
    assert on_disk <= {path for _, _, path in found}



def import_cycles(repo: Path) -> list[tuple[str, ...]]:
    """The import cycles inside each part: the strongly connected pieces (two modules or more) of the graph of
    imports between a part's own modules (every import, as :func:`violations` counts them), each sorted."""
    found = modules(repo)
    names = {module for _, module, _ in found}
    part = {module: owner for owner, module, _ in found}
    graph: dict[str, set[str]] = {module: set() for module in names}
    for owner, module, path in found:
        tree = ast.parse(path.read_text(), filename=str(path))
        for _, name in imported_names(tree, module, path.name == "__init__.py"):
            pieces = name.split(".")
            # the longest prefix that is one of our modules (``from a import b``: a.b or a)
            target = next((".".join(pieces[:k]) for k in range(len(pieces), 1, -1) if ".".join(pieces[:k]) in names),
                          None)
            if target is not None and target != module and part[target] == owner:
                graph[module].add(target)
    # Tarjan's strongly connected components, without recursion
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[tuple[str, ...]] = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                piece = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    piece.append(member)
                    if member == node:
                        break
                if len(piece) > 1:
                    cycles.append(tuple(sorted(piece)))
    return sorted(cycles)


def test_no_part_has_an_import_cycle_inside_it():
    cycles = import_cycles(REPO)
    assert not cycles, ("import cycles inside a part (move what both sides need into a module below both; the check "
                        f"follows deferred and TYPE_CHECKING imports): {cycles}")


def test_the_cycle_check_finds_a_planted_cycle_through_a_deferred_import(tmp_path):
    tree = {**CLEAN_TREE, "phantom/cli/one.py": "def run():\n    from phantom.cli.two import go\n",
            "phantom/cli/two.py": "from phantom.cli import three\n",
            "phantom/cli/three.py": "import phantom.cli.one\n"}
    assert import_cycles(write_tree(tmp_path, tree)) == [("phantom.cli.one", "phantom.cli.three", "phantom.cli.two")]
    clean = tmp_path / "clean"
    clean.mkdir()
    assert import_cycles(write_tree(clean, CLEAN_TREE)) == []

# A small tree in the same layout, with one violation of each kind planted in it.
FAKE_PYPROJECT = """
[tool.setuptools.package-dir]
phantom = "phantom"
"phantom.protocol" = "protocol"
"phantom.model" = "model"
"phantom.scan" = "scan"
"phantom.host" = "host"
"phantom.hil" = "hil"
"""

CLEAN_TREE = {
    "phantom/__init__.py": "class PhantomError(Exception): ...\n",
    "phantom/__main__.py": "from phantom.cli.main import main\n",
    "phantom/cli/__init__.py": "",
    "phantom/cli/main.py": ("import phantom.hil.sim\nfrom phantom.host import daemon\n"
                            "from phantom.scan import compare\n"),
    "protocol/__init__.py": "",
    "protocol/framing.py": "from phantom import PhantomError\nimport numpy\n",
    "model/__init__.py": "",
    "model/fem/__init__.py": "",
    "model/fem/model.py": "from phantom.protocol import framing\nfrom . import kernels\nfrom .. import scene\n",
    "model/fem/kernels.py": "def f():\n    import numba\n",
    "model/scene.py": "",
    "scan/__init__.py": "",
    "scan/compare.py": "from phantom.model.fem import model\n",
    "host/__init__.py": "",
    "host/daemon.py": "from phantom.model import scene\nfrom phantom.protocol.framing import PhantomError\n",
    "hil/__init__.py": "",
    "hil/sim.py": "import phantom.model.fem.model\n",
}

PLANTED = {
    # a function-level import from the model into the host
    "model/fem/kernels.py": ("def f():\n    import numba\n    import phantom.host.daemon\n", "phantom.host.daemon"),
    # the protocol importing the model, in a TYPE_CHECKING block
    "protocol/framing.py": ("from typing import TYPE_CHECKING\n\nif TYPE_CHECKING:\n"
                            "    from phantom.model import scene\n", "phantom.model.scene"),
    # a part imported as a name of the root package
    "hil/sim.py": ("from phantom import host\n", "phantom.host"),
    # a relative import that climbs out of the part
    "host/daemon.py": ("from ..hil import sim\n", "phantom.hil.sim"),
    # a dynamic import
    "scan/compare.py": ("import importlib\n\ndef board():\n    return importlib.import_module('phantom.hil.sim')\n",
                        "phantom.hil.sim"),
    # the scan importing the host
    "scan/__init__.py": ("from phantom.host.daemon import Daemon\n", "phantom.host.daemon.Daemon"),
}


def write_tree(root: Path, files: dict[str, str]) -> Path:
    (root / "pyproject.toml").write_text(FAKE_PYPROJECT)
    for name, text in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return root


def test_a_tree_that_keeps_the_contract_passes(tmp_path):
    broken, unknown = violations(write_tree(tmp_path, CLEAN_TREE))
    assert broken == [] and unknown == []


@pytest.mark.parametrize("planted", sorted(PLANTED))
def test_the_checker_finds_a_planted_violation(tmp_path, planted):
    text, target = PLANTED[planted]
    broken, _ = violations(write_tree(tmp_path, {**CLEAN_TREE, planted: text}))
    assert [(v.path, v.target) for v in broken] == [(planted, target)]


def test_a_part_without_a_rule_is_reported(tmp_path):
    write_tree(tmp_path, {**CLEAN_TREE, "motor/__init__.py": ""})
    (tmp_path / "pyproject.toml").write_text(FAKE_PYPROJECT + '"phantom.motor" = "motor"\n')
    _, unknown = violations(tmp_path)
    assert [part for part, _ in unknown] == ["motor"]


def import_table(text: str) -> dict[str, set[str]]:
    """docs/architecture.md's table of the parts: part -> the parts its "may import" column names in backticks."""
    lines = [line for line in text.splitlines() if line.startswith("|")]
    header = next(index for index, line in enumerate(lines) if "may import" in line)
    column = [cell.strip() for cell in lines[header].split("|")].index("may import")
    table = {}
    for line in lines[header + 2:]:
        cells = line.split("|")
        if len(cells) <= column:
            break
        table[cells[1].strip()] = set(re.findall(r"`(\w+)`", cells[column]))
    return table


def test_the_contract_is_the_one_the_docs_state():
    table = import_table((REPO / "docs" / "architecture.md").read_text())
    for part, allowed in ALLOWED.items():
        assert part in table, f"docs/architecture.md's table of the parts has no row for {part}"
        assert table[part] == allowed - {ROOT}, f"{part}: the docs say {table[part]}, ALLOWED says {allowed}"


#: Paths the architecture page names that the parallel layout work creates (l-host: config.py, model_worker.py;
#: the shape work: shape/). Each must still be missing, so that an entry is deleted the moment its file lands; the
#: lead removes them at the merge.
PENDING: frozenset[str] = frozenset()
#: A path in the repository as the docs write it: a top-level folder, then names (globs allowed).
REPO_PATH = re.compile(r"(?<![\w./-])(?:protocol|model|scan|shape|host|hil|phantom|firmware|tests|bench|docs|"
                       r"scripts)/[\w./*-]*")


def test_every_path_the_architecture_page_names_exists():
    text = (REPO / "docs" / "architecture.md").read_text()
    named = set(REPO_PATH.findall(text))
    assert len(named) > 40
    missing = sorted(path for path in named - PENDING if not any(REPO.glob(path.rstrip("/") or ".")))
    assert not missing, f"docs/architecture.md names paths that do not exist: {missing}"
    landed = sorted(path for path in PENDING if any(REPO.glob(path.rstrip("/"))))
    assert not landed, f"these pending paths exist now: delete them from PENDING in {Path(__file__).name}: {landed}"


# --- the page names every module, and the functions its data path cites exist ---------------------------------

#: The folders of the parts' Python modules (the root's and the CLI's are phantom/).
MODULE_FOLDERS = ("phantom", "protocol", "model", "scan", "shape", "design", "host", "hil")
#: A function, class or module the page cites: a dotted name in backticks under ``phantom.``.
CITED = re.compile(r"`(phantom(?:\.\w+)+)`")


def modules_of(repo: Path) -> list[str]:
    """Every Python module of the parts, as the page writes it (``host/control.py``); a package's
    ``__init__.py`` only for the root."""
    found = []
    for folder in MODULE_FOLDERS:
        for path in sorted((repo / folder).rglob("*.py")):
            relative = path.relative_to(repo).as_posix()
            if "__pycache__" in path.parts or (path.name == "__init__.py" and relative != "phantom/__init__.py"):
                continue
            found.append(relative)
    return found


def modules_without_a_line(text: str, modules: list[str]) -> list[str]:
    """The modules the page's "The modules" tables give no row (a row starts with the module in backticks)."""
    rows = set(re.findall(r"^\| `([\w/.]+\.py)` \|", text, re.MULTILINE))
    return [module for module in modules if module not in rows]


def source_of(dotted: str, repo: Path) -> tuple[Path, list[str]] | None:
    """The file a dotted name under ``phantom.`` lives in and the names left inside it (``phantom.host.control.
    ControlCore.offer`` -> host/control.py, [ControlCore, offer]); None when no module matches."""
    names = dotted.split(".")[1:]
    folders = {"cli": repo / "phantom" / "cli"} | {part: repo / part for part in MODULE_FOLDERS if part != "phantom"}
    if not names or names[0] not in folders:
        return (repo / "phantom" / "__init__.py", names)
    base = folders[names[0]]
    for split in range(len(names), 0, -1):
        folder = base.joinpath(*names[1:split])
        for candidate in ([folder.with_suffix(".py")] if split > 1 else []) + [folder / "__init__.py"]:
            if candidate.is_file():
                return (candidate, names[split:])
    return None


def _defines(body: list[ast.stmt], name: str) -> ast.stmt | None:
    for node in body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and node.name == name:
            return node
        targets = node.targets if isinstance(node, ast.Assign) else [node.target] if isinstance(
            node, ast.AnnAssign) else []
        if any(isinstance(target, ast.Name) and target.id == name for target in targets):
            return node
    return None


def unresolved(text: str, repo: Path) -> list[str]:
    """The names the page cites in backticks (``phantom.x.y.Name.attr``) that name no module, function, class,
    method or module-level value in the source (read with ``ast``: nothing is imported)."""
    missing = []
    for dotted in sorted(set(CITED.findall(text))):
        found = source_of(dotted, repo)
        if found is None:
            missing.append(dotted)
            continue
        path, names = found
        body: list[ast.stmt] = ast.parse(path.read_text()).body
        for name in names:
            node = _defines(body, name)
            if node is None:
                missing.append(dotted)
                break
            body = node.body if isinstance(node, ast.ClassDef) else []
    return missing


def test_the_architecture_page_names_every_module():
    missing = modules_without_a_line((REPO / "docs" / "architecture.md").read_text(), modules_of(REPO))
    assert not missing, ("docs/architecture.md has no line for these modules: add a row `| `PATH` | what it holds |` "
                         f"to its part's table under \"The modules\": {missing}")


def test_a_module_left_out_of_the_page_is_named(tmp_path):
    (tmp_path / "host").mkdir()
    for name in ("__init__.py", "control.py", "corrections.py"):
        (tmp_path / "host" / name).write_text('"""x"""\n')
    page = "| host | what it holds |\n|---|---|\n| `host/control.py` | the control core |\n"
    assert modules_of(tmp_path) == ["host/control.py", "host/corrections.py"]
    assert modules_without_a_line(page, modules_of(tmp_path)) == ["host/corrections.py"]


def test_every_function_the_architecture_page_cites_exists():
    text = (REPO / "docs" / "architecture.md").read_text()
    assert len(set(CITED.findall(text))) >= 20
    missing = unresolved(text, REPO)
    assert not missing, f"docs/architecture.md cites names the source does not define: {missing}"


def test_a_cited_function_that_does_not_exist_is_named(tmp_path):
    (tmp_path / "host").mkdir()
    (tmp_path / "host" / "daemon.py").write_text(
        "LIMIT = 1\n\nclass Daemon:\n    ready: bool\n\n    async def set_target(self):\n        pass\n")
    page = ("`phantom.host.daemon.Daemon.set_target` `phantom.host.daemon.Daemon.ready` `phantom.host.daemon.LIMIT` "
            "`phantom.host.daemon.Daemon.apply_target` `phantom.host.daemon` `phantom.host.nothing.f` "
            "`phantom.host.daemon.Daemon.set_target.inner`")
    assert unresolved(page, tmp_path) == ["phantom.host.daemon.Daemon.apply_target",
                                          "phantom.host.daemon.Daemon.set_target.inner", "phantom.host.nothing.f"]
