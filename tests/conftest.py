"""Fixtures shared by several test files, and what running on several processes (pytest-xdist) needs.

`make check` and `make test` run pytest on every core (``-n auto``). Each worker is its own process with its own
session fixtures; the on-disk caches (``phantom.cache_dir``) are shared, and every cache entry is written to a
temporary file and renamed into place, so a reader never sees half of one. What is expensive to build is built
under :func:`machine_lock`, so that two workers do not build it twice at once. The tests that run simavr (marked
``sim``) pace the simulated board to the wall clock, and a daemon beside the board must answer it within its
dead-host deadline: `make test` runs them in a pytest of their own, at a higher priority than the others
(scripts/pytest-all.sh).
"""

import ast
import fcntl
import gc
import itertools
import os
import re
import resource
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

import phantom

# The shape model's programs are JAX's, compiled op by op when they first run: JAX's persistent compilation cache
# (keyed by the program, JAX's version and the device) in the phantom cache folder keeps them for the next run, in
# this process and the commands the tests start. Measured: initialising a small VAE 7.5 -> 0.35 s CPU; the shape
# and loader tests of make check 16.0 -> 9.8 s CPU. Set before anything imports jax.
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(phantom.cache_dir("jax")))
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "0")


# How xdist hands out the tests (tests/README.md, "Scheduling"). Two rules:
#
# - A module whose tests share a module-scoped fixture runs on one worker, in file order: the fixture is then
#   built once (test_shape_analysis's VAE was trained on both workers, 25 s each), and the simavr modules' shared
#   board or daemon sees its tests in the order they were written for (test_daemon_e2e's recording holds what its
#   earlier tests logged). Every other test is a work unit of its own. The modules are named here because the
#   scheduler, in pytest's controlling process, sees test ids only; pytest_collection_modifyitems refuses a test
#   that shares such a fixture outside them.
# - The longest work starts first (units with a simavr test marked slow, then with a slow test, and within each
#   the modules kept together, most tests first), so that none of it is left running alone at the end.
KEPT_TOGETHER = frozenset(f"tests/{name}.py" for name in (
    "test_daemon_board_promises", "test_daemon_corrections", "test_daemon_e2e", "test_daemon_scene_promises",
    "test_shape_target_sim",
    "test_examples", "test_fem_corotational", "test_fem_felupe", "test_fem_gravity", "test_fem_hyperelastic",
    "test_fem_kernels", "test_fem_limit_point", "test_fem_output", "test_fem_pathfollow", "test_fem_quadratic",
    "test_fidelity",
    "test_hil_boot", "test_hil_sim", "test_inverse_fem", "test_inverse_gent", "test_loader_fuzz", "test_mesh",
    "test_model_prostate", "test_motion_sim", "test_packaging", "test_python_api", "test_readme_commands",
    "test_recording", "test_report", "test_response", "test_scan", "test_scan_bumped", "test_scan_calibrate",
    "test_scan_capture",
    "test_scan_hull_bias", "test_scan_hung", "test_scan_reconstruct", "test_scan_rig_sim", "test_scene_run_timeline",
    "test_shape_analysis",
    "test_shape_data", "test_sim_truth_verify", "test_panel_browser"))


#: The markers that -m expressions select on (pyproject.toml registers them).
SELECTING_MARKERS = ("sim", "slow", "long", "busy_cores")


def _module_markers(path: Path) -> set[str]:
    """The SELECTING_MARKERS that a test module's ``pytestmark`` gives all its tests, read from its source."""
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.Assign) and any(isinstance(target, ast.Name) and target.id == "pytestmark"
                                                for target in node.targets):
            return {part.attr for part in ast.walk(node.value) if isinstance(part, ast.Attribute)
                    and part.attr in SELECTING_MARKERS and isinstance(part.value, ast.Attribute)
                    and part.value.attr == "mark"}
    return set()


def pytest_ignore_collect(collection_path: Path, config: pytest.Config) -> bool | None:
    """A test module whose ``pytestmark`` leaves the -m expression no test to select is not imported: collecting
    test_shape_analysis imported JAX (1 s in each worker) for no test of make check. Its tests can only add
    markers to the module's, so the module is left out only where the expression is false with every set of
    markers its tests could have; an expression naming another marker leaves every module in."""
    try:  # pytest's own parser of -m (not public API: without it, every module is imported)
        from _pytest.mark.expression import Expression
    except ImportError:
        return None
    expression = config.getoption("markexpr")
    if not expression or not (collection_path.name.startswith("test_") and collection_path.suffix == ".py"):
        return None
    if set(re.findall(r"[A-Za-z_]\w*", expression)) - {"and", "or", "not", *SELECTING_MARKERS}:
        return None
    markers = _module_markers(collection_path)
    if not markers:
        return None
    others = [marker for marker in SELECTING_MARKERS if marker not in markers]
    try:
        compiled = Expression.compile(expression)
        for count in range(len(others) + 1):
            for added in itertools.combinations(others, count):
                if compiled.evaluate((markers | set(added)).__contains__):
                    return None
    except (AttributeError, TypeError, ValueError, SyntaxError):  # another pytest's parser, or a bad expression
        return None
    return True


def work_unit(nodeid: str) -> str:
    """The unit a worker runs whole: the module for the modules kept together, else the test itself."""
    module = nodeid.split("::", 1)[0]
    return module if module in KEPT_TOGETHER else nodeid


#: The session fixtures that build into the machine's cache what a cold one lacks (minutes on two busy cores; the
#: other workers wait on its lock): a test that uses one is timed from its call, not its setup. On a cold cache in
#: a clean clone's make test, the calibrated table's build (shipped with its scene since) took 293 s of the 300 a
#: test is given.
MACHINE_BUILDS = frozenset({"default_model_cached"})

#: Where pytest's cache keeps each test's last measured duration (s, setup, call and teardown together).
DURATIONS_KEY = "phantom/durations_s"
_measured_s: dict[str, float] = {}


def measured_first_key(tests: Iterable[str], measured_s: dict[str, float]) -> float:
    """A work unit's place when units go longest first by their last measured duration (sort ascending): minus
    the sum of its tests' durations, or minus infinity (first) where a test was never measured."""
    durations_s = [measured_s.get(nodeid) for nodeid in tests]
    return -float("inf") if None in durations_s else -sum(d for d in durations_s if d is not None)


def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """pytest-xdist's scheduler by work units (``--dist loadgroup`` and ``xdist_group`` do not work with pytest 9:
    xdist renames ``item._nodeid``, which pytest 9 no longer reads); units are handed out longest first by the
    durations the last runs measured (:func:`measured_first_key`), else in the order pytest_collection_modifyitems
    sorts them. (The queue of units is reordered, in this controlling process, not the collection: xdist names a
    worker's tests by their places in its own collection.)"""
    if config.getoption("dist") != "load":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class WorkUnitScheduling(LoadScopeScheduling):
        queue_ordered = False

        def _split_scope(self, nodeid: str) -> str:
            return work_unit(nodeid)

        def _assign_work_unit(self, node: Any) -> None:
            # the first call comes once schedule() has queued every unit, before any is handed out
            if not self.queue_ordered:
                self.queue_ordered = True
                measured_s = config.cache.get(DURATIONS_KEY, {}) if getattr(config, "cache", None) is not None else {}
                if measured_s:
                    units = sorted(self.workqueue.items(), key=lambda unit: measured_first_key(unit[1], measured_s))
                    self.workqueue.clear()
                    self.workqueue.update(units)
            super()._assign_work_unit(node)

    config.option.loadscopereorder = False   # keep the collection's order, not the units' sizes
    return WorkUnitScheduling(config, log)


def _module_scoped_fixtures(item: pytest.Item) -> list[str]:
    """The fixtures of a scope wider than a test that ``item`` uses and its own module defines."""
    module = item.nodeid.split("::", 1)[0]
    return [name for name, definitions in item._fixtureinfo.name2fixturedefs.items()
            if definitions and definitions[-1].scope in ("module", "class")
            and definitions[-1].baseid.split("::", 1)[0] == module]


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Refuse a test that shares a module-scoped fixture outside KEPT_TOGETHER, then sort the work units longest
    first (stable: a unit's tests keep their file order)."""
    for item in items:
        if work_unit(item.nodeid) == item.nodeid and (shared := _module_scoped_fixtures(item)):
            raise pytest.UsageError(
                f"{item.nodeid} shares the module-scoped fixture(s) {', '.join(shared)}: add its module to "
                f"KEPT_TOGETHER in tests/conftest.py, so that its tests run on one worker in file order")

    for item in items:  # a build once per machine times its own setup, not the test's budget (MACHINE_BUILDS)
        if MACHINE_BUILDS & set(getattr(item, "fixturenames", ())):
            marker = item.get_closest_marker("timeout")
            timeout_s = config.getini("timeout")
            if marker is not None:
                timeout_s = marker.args[0] if marker.args else marker.kwargs.get("timeout", timeout_s)
            item.add_marker(pytest.mark.timeout(float(timeout_s), func_only=True), append=False)

    def rank(item: pytest.Item) -> int:
        slow = item.get_closest_marker("slow") is not None
        return 0 if slow and item.get_closest_marker("sim") is not None else 1 if slow else 2

    unit_rank: dict[str, int] = {}
    unit_size: dict[str, int] = {}
    for item in items:
        unit = work_unit(item.nodeid)
        unit_rank[unit] = min(unit_rank.get(unit, 2), rank(item))
        unit_size[unit] = unit_size.get(unit, 0) + 1
    # within a rank, the modules kept together first, the largest first: single tests fill in around them at the
    # end (make check's workers had finished a module's tests alone, the other idle)
    items.sort(key=lambda item: (unit_rank[work_unit(item.nodeid)], -unit_size[work_unit(item.nodeid)]))


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--cpu-durations", type=int, default=None, metavar="N",
                     help="list the N tests that took the most CPU time (the test's process and the commands it "
                          "waited for; setup, call and teardown together)")


def _cpu_s() -> float:
    """CPU seconds of this process and of the child processes it has waited for."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


# --durations measures the wall clock, which on a loaded machine measures the load (the mutated-scene fuzz: 0.25 s
# of CPU, and 190 s of wall clock in one run at a load of 24): --cpu-durations says what the test itself costs.
@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
    item.stash[_CPU_AT_START] = _cpu_s()
    return (yield)


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    """Each test's duration, for the next run's order (in the controlling process, from every worker's reports)."""
    _measured_s[report.nodeid] = _measured_s.get(report.nodeid, 0.0) + report.duration


def pytest_sessionfinish(session: pytest.Session) -> None:
    """The durations measured, added to those of earlier runs in pytest's cache (by the controlling process)."""
    cache = getattr(session.config, "cache", None)  # None: pytest -p no:cacheprovider
    if cache is None or hasattr(session.config, "workerinput") or not _measured_s:
        return
    cache.set(DURATIONS_KEY, {**cache.get(DURATIONS_KEY, {}), **_measured_s})


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Iterator[pytest.TestReport]:
    report = yield
    if call.when == "teardown" and _CPU_AT_START in item.stash:
        report.user_properties.append(("cpu_s", _cpu_s() - item.stash[_CPU_AT_START]))
    return report


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter, config: pytest.Config) -> None:
    count = config.getoption("--cpu-durations")
    if not count:
        return
    costs = [(dict(report.user_properties)["cpu_s"], report.nodeid)
             for reports in terminalreporter.stats.values() for report in reports
             if getattr(report, "when", None) == "teardown" and "cpu_s" in dict(getattr(report, "user_properties", []))]
    terminalreporter.write_sep("=", f"{min(count, len(costs))} tests that took the most CPU")
    for cpu_s, nodeid in sorted(costs, reverse=True)[:count]:
        terminalreporter.write_line(f"{cpu_s:8.2f}s cpu  {nodeid}")
    terminalreporter.write_line(f"{sum(cost for cost, _ in costs):8.2f}s cpu in all {len(costs)} tests")


_CPU_AT_START = pytest.StashKey[float]()


@contextmanager
def machine_lock(name: str) -> Iterator[None]:
    """Hold an exclusive lock named ``name`` (a file under ``phantom.cache_dir("locks")``) across processes."""
    with open(phantom.cache_dir("locks") / f"{name}.lock", "w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


@pytest.fixture(autouse=True, scope="session")
def _measured_volumes_of_the_session_only(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """The user's data directory (the stored measurements every daemon corrects its model with) is one of the
    session's: a daemon a test starts neither reads the measurements a person stored on this machine nor adds to
    them. A test of its own store sets PHANTOM_DATA_DIR again."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("PHANTOM_DATA_DIR", str(tmp_path_factory.mktemp("phantom-data")))
        yield


@pytest.fixture(autouse=True)
def _measured_volumes_of_the_test_only(tmp_path_factory: pytest.TempPathFactory,
                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """... and each test's own: measurements a test stored (a verified target's scans, a characterisation) would
    otherwise correct the model of every daemon started after it in the same session (test_scan_validate_sim's
    inverse answered 26.50 ml for 27 on a model corrected by an earlier test's scans). A fixture wider than a
    test sees the session's."""
    monkeypatch.setenv("PHANTOM_DATA_DIR", str(tmp_path_factory.mktemp("phantom-data")))


@pytest.fixture
def data_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A command line's data and cache folders in the test's own (a refusal builds no model, so a cold cache costs
    nothing), run from that folder; the data folder. A module that needs the model's warm cache has its own."""
    monkeypatch.setenv("PHANTOM_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.setenv("PHANTOM_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.chdir(tmp_path)
    return tmp_path / "data"


@pytest.fixture(autouse=True)
def _no_long_collections_during_a_simulated_board(request: pytest.FixtureRequest) -> None:
    """Before a test that runs simavr: collect, then freeze what survives, so that no full garbage collection
    scans it again. The sim tests share one long pytest process whose heap grows with every test before them;
    its full collections held the GIL for 150-180 ms, long enough, with a loaded machine, for the link's
    keepalive to miss the board's host deadline (then 500 ms of board time, 250 ms of wall time at speed 2; now
    500 ms of wall time at any speed) and for the board to latch DEAD_HOST mid-test (a 350 ms collection latched
    it in both tries)."""
    if request.node.get_closest_marker("sim") is not None:
        gc.collect()
        gc.freeze()


@pytest.fixture
def dask_scheduler() -> Iterator[str]:
    """The address of a two-worker LocalCluster of the test's own. Not the session's: a cluster starts and closes
    in about a second and 1.5 CPU-seconds, but idle it takes about a tenth of a core (its workers' heartbeats
    and statistical profilers, its scheduler's loop in the pytest worker), and a session's lived on from its first
    test to the end of the run (two of them, in two workers, in make test)."""
    from phantom.model.cluster import local_cluster

    cluster = local_cluster(2)
    yield cluster.scheduler_address
    cluster.close()


def calibrated_without_its_table(folder: Path) -> Path:
    """A copy of ``builtin:calibrated`` in ``folder`` without the table files it ships: a scene whose table is
    built once per machine (145 CPU-seconds), for the tests of a daemon that builds one."""
    from phantom.model import load_scene
    from phantom.model.calibration.calibrate import dump_toml
    from phantom.model.scene import without_shipped_tables

    raw = load_scene("builtin:calibrated").raw
    assert "table_volumes" in raw["model"], "builtin:calibrated names its table files no longer"
    path = folder / "calibrated_unshipped.toml"
    path.write_text(dump_toml(without_shipped_tables(raw)))
    return path


@pytest.fixture(scope="session")
def default_model_cached():
    """The model of a daemon started with its defaults and of the example scenes (``builtin:converged``), meshed
    and its rest compliance computed into the disk cache, so that a daemon a test starts does not spend its
    start-up deadline meshing (tens of seconds the first time on a machine); its table's volumes and shapes ship
    with it. The other workers wait for it and read it from the cache."""
    from phantom.model import PhantomModel, load_scene

    with machine_lock("default-model"):
        model = PhantomModel.from_scene(load_scene("builtin:converged"))
        model.compliance()
        return model

