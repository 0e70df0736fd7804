"""The daemon's parts on their own: the scene runner on a fake clock, the estimate schedule, the simulated
board's keeper, the model worker's life, logging levels for journald, the neutral command-line values."""

import asyncio
import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import calibrated_without_its_table
from daemon_standins import CHAMBERS, DaemonStandIns, FakeClock, ModelInProcess, model_info

from phantom import PhantomError
from phantom.cli.common import output_file
from phantom.host.estimation import ESTIMATE_CHANGE_PA, EstimateSchedule
from phantom.host.processes import child_pids, descendants
from phantom.host.scene_runner import SceneRunner, prepare_run
from phantom.model.errors import SceneError


def runner_with_events():
    clock, events = FakeClock(), []
    return clock, events, SceneRunner(clock, lambda kind, text, level: events.append(text))


SCENE = {"timeline": {"end_s": 30}, "steps": [{"at_s": 0, "volume_ml": 30},
                                              {"at_s": 10, "ramp_s": 4, "volume_ml": 34}]}


def test_the_scene_runner_follows_its_clock_scaled_and_finishes_at_the_end():
    clock, events, runner = runner_with_events()
    started = runner.start(SCENE, "bph", CHAMBERS, time_scale=2.0)
    assert started["wall_duration_s"] == 15.0 and runner.active
    assert runner.tick().to_json() == {"volume_ml": 30.0}
    clock.now_s += 6.0                       # 12 s of scene time: half-way up the ramp
    assert runner.tick().values == pytest.approx((32e-6,))
    assert [step.index for step in runner.run.steps] == [0, 1]
    assert runner.scene_time_s() == pytest.approx(12.0)
    clock.now_s += 9.0                       # 30 s of scene time: the end
    assert runner.tick() is None and not runner.active and runner.scene_time_s() is None
    assert any("finished" in text for text in events)


def test_a_step_records_when_the_core_said_it_was_reached_once_and_the_last_estimate():
    """When a step is reached is the control core's rule (tests/test_control_core.py); the runner books it."""
    clock, _, runner = runner_with_events()
    runner.start(SCENE, "bph", CHAMBERS, time_scale=1.0)
    runner.tick()
    clock.now_s += 2.0
    runner.observe(29.8, true_volume_ml=29.9)
    runner.reached(0)
    clock.now_s += 1.0
    runner.reached(0)                        # told again (the board came back): the first time stays
    first = runner.run.steps[0].to_json()
    assert first["reached_after_s"] == pytest.approx(2.0) and first["true_volume_ml"] == 29.9
    assert first["error_pct"] == pytest.approx(100 * (29.8 - 30) / 30)
    runner.reached(5)                        # no such step: nothing
    assert runner.run.steps[0].reached_after_s == pytest.approx(2.0)


def test_a_stopped_scene_gives_no_target_and_bad_scenes_are_refused():
    clock, events, runner = runner_with_events()
    runner.start(SCENE, "bph", CHAMBERS, 1.0)
    runner.stop("vented")
    assert runner.tick() is None and "scene bph stopped: vented" in events
    with pytest.raises(SceneError, match="no \\[\\[steps\\]\\]"):
        runner.start({}, "empty", CHAMBERS, 1.0)
    with pytest.raises(SceneError, match="end_s must be a number from 14 s .* to 604800 s .*got 5"):
        runner.start({**SCENE, "timeline": {"end_s": 5}}, "short", CHAMBERS, 1.0)
    with pytest.raises(SceneError, match="end_s must be a number from 14 s .*got 1000000"):   # it overflowed a float
        runner.start({**SCENE, "timeline": {"end_s": 10**400}}, "long", CHAMBERS, 1.0)
    with pytest.raises(SceneError, match="time_scale must be a positive"):
        runner.start(SCENE, "bph", CHAMBERS, float("nan"))


def test_a_stopped_scene_says_it_was_stopped_and_why_and_its_time_stands_where_it_stopped():
    """A scene stopped by another request was shown "finished", its time going on after the stop: a client waiting
    for it (``run-scene --wait``) took the stop for its end and reported success."""
    clock, _, runner = runner_with_events()
    runner.start(SCENE, "bph", CHAMBERS, 2.0)
    runner.tick()
    clock.now_s += 3.0
    runner.stop("a set_target request")
    clock.now_s += 5.0
    stopped = runner.run.to_json(clock())
    assert stopped["finished"] and stopped["stopped"] == "a set_target request"
    assert stopped["time_s"] == pytest.approx(6.0)
    runner.start(SCENE, "bph", CHAMBERS, 2.0)
    clock.now_s += 15.0
    runner.tick()
    ended = runner.run.to_json(clock())
    assert ended["finished"] and ended["stopped"] is None and ended["time_s"] == 30.0


def test_the_schedule_estimates_on_change_or_once_a_second_and_shapes_only_when_wanted():
    schedule = EstimateSchedule(mesh_hz=2.0)
    assert schedule.due(0.0, wants_shape=False) is None          # no telemetry yet
    for board_ms in range(0, 1000, 20):
        schedule.add(board_ms / 1e3, np.array([1000.0, 1000.0, 1000.0]))
    assert len(schedule.window) == 26                            # the last 0.5 s of board time
    first = schedule.due(0.0, wants_shape=False)
    assert first is not None and not first.with_shape
    assert schedule.due(0.1, wants_shape=False) is None          # one at a time
    schedule.finished()
    assert schedule.due(0.2, wants_shape=False) is None          # nothing moved
    schedule.add(1.0, np.array([1000.0, 1000.0, 1000.0 + 40 * ESTIMATE_CHANGE_PA]))
    assert schedule.due(0.3, wants_shape=False) is not None      # the mean moved
    schedule.finished()
    assert schedule.due(1.4, wants_shape=False) is not None      # a second old
    schedule.finished()
    # shapes: never unless wanted; then at mesh_hz
    shapes = 0
    for tick in range(100):                                      # 10 s at 10 Hz
        request = schedule.due(2.0 + tick / 10, wants_shape=True)
        if request is not None:
            shapes += request.with_shape
            schedule.finished()
    assert shapes == 20
    schedule.clear()
    assert schedule.due(20.0, wants_shape=True) is None


class DyingBoard:
    """A stand-in for SimulatedBoard (a unit test of the keeper alone): answers until told to die."""

    made = []

    def __init__(self, speed):
        self.alive, self.speed = True, speed
        DyingBoard.made.append(self)

    def start(self):
        import tempfile

        self.folder = tempfile.mkdtemp()
        self.port = os.path.join(self.folder, "tty")
        open(self.port, "w").close()

    def stop(self):
        self.alive = False

    def plant_state(self):
        if not self.alive:
            raise BrokenPipeError("the harness is gone")
        return {"gland_volume_ml": 31.5}


def test_the_keeper_restarts_a_dead_simulator_behind_the_same_port(monkeypatch):
    import asyncio

    from phantom.host import sim_board

    monkeypatch.setattr(sim_board, "WATCH_PERIOD_S", 0.01)
    DyingBoard.made.clear()
    events = []
    keeper = sim_board.SimulatedBoardKeeper(1.0, lambda kind, text, level: events.append((text, level)),
                                            board_factory=DyingBoard)
    keeper.start()
    first_target = os.readlink(keeper.port)

    async def scenario():
        watch = asyncio.create_task(keeper.watch())
        await asyncio.sleep(0.05)
        assert keeper.plant_volume_ml == 31.5
        DyingBoard.made[0].alive = False
        for _ in range(200):
            await asyncio.sleep(0.01)
            if keeper.restarts:
                break
        watch.cancel()

    asyncio.run(scenario())
    assert keeper.restarts == 1 and len(DyingBoard.made) == 2
    assert os.readlink(keeper.port) != first_target and os.readlink(keeper.port) == DyingBoard.made[1].port
    assert ("the simulated board (simavr) died: restarting it", "ERROR") in events
    keeper.close()
    assert not os.path.exists(keeper.port)


def test_plant_volume_is_read_only_when_the_plant_reports_it():
    from phantom.host.sim_board import plant_volume_ml

    assert plant_volume_ml({"gland_volume_ml": 40}) == 40.0
    assert plant_volume_ml({"pressures_pa": [0, 0, 0]}) is None


WORKER_PARENT = """
import asyncio, os, sys, time
from phantom.host.model_worker import worker_pool
pool = worker_pool()
print(pool.submit(os.getpid).result(), flush=True)
time.sleep(60)
"""


def test_the_model_worker_dies_with_its_parent_even_on_sigkill():
    parent = subprocess.Popen([sys.executable, "-c", WORKER_PARENT], stdout=subprocess.PIPE, text=True)
    try:
        worker_pid = int(parent.stdout.readline())
        os.kill(worker_pid, 0)                                  # alive while its parent is
        parent.send_signal(signal.SIGKILL)
        parent.wait(10)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            try:
                os.kill(worker_pid, 0)
            except ProcessLookupError:
                break
            time.sleep(0.05)
        else:
            os.kill(worker_pid, signal.SIGKILL)
            pytest.fail("the model worker outlived its killed parent")
    finally:
        if parent.poll() is None:
            parent.kill()


def test_children_and_descendants_are_listed_while_other_processes_come_and_go():
    # the table build's SIGTERM handler kills the children it lists: one that ended between the listing and its read
    # raised FileNotFoundError there (a thread of the build's, then), and the build ended through Python's slow
    # exit (3.8 s of the daemon's 5 s wait, a clean clone's make test). Processes ending meanwhile, here: a listing
    # of /proc read without care failed on 97 % of tries beside them
    parent = subprocess.Popen([sys.executable, "-c", "import subprocess, sys, time\n"
                               "child = subprocess.Popen(['sleep', '30'])\nprint(child.pid, flush=True)\n"
                               "time.sleep(30)"], stdout=subprocess.PIPE, text=True)
    grandchild = int(parent.stdout.readline())
    churning = True

    def churn() -> None:
        while churning:
            subprocess.run(["true"], check=True)

    churners = [threading.Thread(target=churn) for _ in range(2)]
    for thread in churners:
        thread.start()
    try:
        listings, deadline = 0, time.monotonic() + 0.5
        while time.monotonic() < deadline:
            assert parent.pid in child_pids() and grandchild not in child_pids()
            assert child_pids(parent.pid) == [grandchild] and grandchild in descendants(os.getpid())
            listings += 1
        assert listings > 5
    finally:
        churning = False
        for thread in churners:
            thread.join()
        parent.kill()
        parent.wait()
        os.kill(grandchild, signal.SIGKILL)


def test_under_systemd_levels_are_journald_priorities_on_every_line(capfd, monkeypatch):
    from phantom.host.logs import configure_logging

    status = os.fstat(sys.stderr.fileno())
    monkeypatch.setenv("JOURNAL_STREAM", f"{status.st_dev}:{status.st_ino}")
    configure_logging("info")
    log = logging.getLogger("phantom.host.daemon")
    log.debug("not shown")
    log.info("link up")
    log.warning("link lost")
    try:
        raise ValueError("boom")
    except ValueError:
        log.exception("control tick failed")
    lines = capfd.readouterr().err.splitlines()
    assert lines[0] == "<6>phantom.host.daemon: link up" and lines[1] == "<4>phantom.host.daemon: link lost"
    assert lines[2] == "<3>phantom.host.daemon: control tick failed"
    assert len(lines) > 4 and all(line.startswith("<3>") for line in lines[3:])      # the traceback, as errors
    assert "ValueError: boom" in lines[-1]
    monkeypatch.delenv("JOURNAL_STREAM")
    configure_logging("warning")
    log.info("quiet")
    log.error("loud")
    err = capfd.readouterr().err
    assert "quiet" not in err and "ERROR phantom.host.daemon: loud" in err and not err.startswith("<")
    with pytest.raises(ValueError, match="unknown log level"):
        configure_logging("chatty")
    configure_logging("info")


def test_output_files_get_their_folders(tmp_path):
    assert output_file(tmp_path / "new" / "deeper" / "out.json") == tmp_path / "new" / "deeper" / "out.json"
    assert (tmp_path / "new" / "deeper").is_dir()
    (tmp_path / "file").write_text("")
    with pytest.raises(PhantomError, match="cannot create the folder"):
        output_file(tmp_path / "file" / "out.json")


def modules_loaded(imports: str, prefixes: tuple[str, ...]) -> list[str]:
    """The modules under ``prefixes`` that a fresh interpreter has loaded after ``import <imports>``."""
    code = (f"import sys, json, {imports}; "
            f"print(json.dumps(sorted(m for m in sys.modules if m.startswith({prefixes!r}))))")
    return json.loads(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                                     check=True).stdout)


def test_the_model_package_does_not_import_the_host_package():
    assert modules_loaded("phantom.model.inverse, phantom.cli.inverse, phantom.cli.model", ("phantom.host",)) == []


def test_the_daemon_loads_neither_the_hil_package_nor_the_command_line():
    """The host is joined to the simulated board by the command line, which passes the board's factory."""
    assert modules_loaded("phantom.host.service, phantom.host.handlers", ("phantom.hil", "phantom.cli")) == []


def test_a_daemon_told_to_simulate_without_a_board_factory_refuses_before_it_takes_the_socket(tmp_path):
    import asyncio

    from phantom.host.config import DaemonConfig
    from phantom.host.service import start_daemon

    config = DaemonConfig(sim=True, socket=tmp_path / "d.sock")
    with pytest.raises(PhantomError, match="cannot simulate a board: start the daemon with `phantom daemon --sim`"):
        asyncio.run(start_daemon(config))
    assert not (tmp_path / "d.sock").exists()


# --- the daemon's wiring, one layer, with stand-ins for the parts it is given ---------------------------------

class PartsStandIn(DaemonStandIns):
    """Stand-ins for the daemon's parts (a unit test of the wiring alone; end to end they are real): a model whose
    scene asks for shapes or not, a board that refuses ZERO_SENSORS with ``refuse_zero_with`` (its first
    ``refusals`` tries; None: every one)."""

    def __init__(self, scene_shape: bool, refuse_zero_with: str | None = None, refusals: int | None = None):
        super().__init__(model_info(26.1, "updated", "scene.toml", wants_shape=scene_shape))
        self.refuse_zero_with, self.refusals = refuse_zero_with, refusals

    def answer(self, name):
        from phantom.host.session import CommandRejected

        zero_tries = self.commands.count("ZERO_SENSORS")
        if name == "ZERO_SENSORS" and self.refuse_zero_with and (self.refusals is None or zero_tries <= self.refusals):
            raise CommandRejected(name, self.refuse_zero_with)
        return "OK"


def frame(board_time_ms: int, kpa: float):
    from types import SimpleNamespace

    pressures = np.full(3, kpa * 1e3)
    return SimpleNamespace(board_time_ms=board_time_ms, pressures_pa=pressures, setpoints_pa=pressures,
                           drive_levels=np.zeros(3), states=["HOLD"] * 3, fault_flags=0)


async def run_control(daemon, clock, seconds: float):
    """Telemetry at 50 Hz and the estimate tick at 10 Hz on the fake clock, with a rising pressure."""
    import asyncio

    for tick in range(int(seconds * 10)):
        for sub in range(5):
            daemon.on_telemetry(frame(tick * 100 + sub * 20, 0.1 * tick))
        clock.now_s += 0.1
        daemon.estimates.tick(daemon.now_s(), clock(), daemon.wants_shape(), daemon.spawn)
        for _ in range(3):
            await asyncio.sleep(0)


@pytest.mark.parametrize(("scene_shape", "recording", "meshes"), [
    (False, True, 0), (True, False, 0), (True, True, 20)])
def test_a_shape_is_computed_and_logged_only_when_the_scene_asks_and_something_records(scene_shape, recording,
                                                                                        meshes):
    import asyncio

    parts, clock = PartsStandIn(scene_shape), FakeClock()
    daemon = parts.daemon(clock, rerun_save="x.rrd" if recording else None, mesh_hz=2.0)
    asyncio.run(run_control(daemon, clock, 10.0))
    shapes_asked = sum(1 for call in parts.calls if call == ("estimate", True))
    logged = [call for call in parts.calls if call[0] in ("log_mesh", "log_rest_surface")]
    # at --mesh-hz 2 over 10 s: 20 at most (a tick's float rounding can push one shape to the next tick)
    assert (15 <= shapes_asked <= meshes) if meshes else shapes_asked == 0
    assert daemon.estimates.meshes_logged == shapes_asked == sum(1 for call in logged if call[0] == "log_mesh")
    if meshes:
        # the rest shape once, before the first deformed mesh
        assert [call[0] for call in logged[:2]] == ["log_rest_surface", "log_mesh"]
        assert sum(1 for call in logged if call[0] == "log_rest_surface") == 1


@pytest.mark.parametrize(("status", "reason"), [
    ("NOT_VENTED", "vent first"), ("NOT_SETTLED", "not steady"), ("ZERO_OUT_OF_RANGE", "old zero is kept"),
    ("SOMETHING_NEW", "the board answered SOMETHING_NEW")])
def test_a_refused_zero_says_why(status, reason):
    import asyncio

    from phantom.host.api import ApiError

    parts = PartsStandIn(False, refuse_zero_with=status)
    daemon = parts.daemon()
    with pytest.raises(ApiError, match=f"{status}.*{reason}") as refused:
        asyncio.run(daemon.zero.sensors())
    assert refused.value.code == "rejected"


@pytest.mark.parametrize(("refusals", "zeroed"), [(3, True), (None, False)])
def test_after_connecting_a_board_not_yet_settled_is_asked_again_until_the_limit(monkeypatch, refusals, zeroed):
    import asyncio

    import phantom.host.zeroing as zeroing

    monkeypatch.setattr(zeroing, "ZERO_RETRY_S", 0.01)
    monkeypatch.setattr(zeroing, "ZERO_SETTLE_LIMIT_S", 0.4)
    parts = PartsStandIn(False, refuse_zero_with="NOT_SETTLED", refusals=refusals)
    daemon = parts.daemon()
    asyncio.run(daemon.zero.after_connecting())
    tries = sum(1 for call in parts.calls if call == ("command", "ZERO_SENSORS"))
    texts = [event["text"] for event in daemon.events]
    if zeroed:  # three NOT_SETTLED, then the zero is taken
        assert tries == 4 and any("sensors zeroed after connecting" in text for text in texts)
        assert daemon.status()["zero"]["state"] == "zeroed"
    else:  # never still (no telemetry here): asked every 4 waits until the limit, then said once
        assert 5 <= tries <= 11 and any("not zeroed after connecting" in text and "NOT_SETTLED" in text
                                         for text in texts)
        assert daemon.status()["zero"]["state"] == "missing"


def test_a_main_task_that_fails_is_logged_and_stops_the_daemon_with_status_1(caplog):
    import asyncio
    import functools

    from phantom.host import service

    parts = PartsStandIn(False)
    daemon = parts.daemon()

    async def broken():
        raise RuntimeError("the link task broke")

    async def scenario():
        task = asyncio.create_task(broken(), name="link")
        task.add_done_callback(functools.partial(service._task_ended, daemon))
        await asyncio.sleep(0.01)

    phantom_logger = logging.getLogger("phantom")
    propagate, phantom_logger.propagate = phantom_logger.propagate, True   # so that caplog sees the records
    try:
        with caplog.at_level(logging.ERROR, logger="phantom"):
            asyncio.run(scenario())
    finally:
        phantom_logger.propagate = propagate
    assert daemon.stopping.is_set() and daemon.exit_code == 1
    record = next(record for record in caplog.records if "ended unexpectedly" in record.getMessage())
    assert record.exc_info and "the link task broke" in str(record.exc_info[1])


@pytest.mark.slow
def test_a_volume_ramp_gives_setpoints_that_rise_smoothly_to_the_inverses_answer():
    """Each point of a 30 -> 35 ml ramp solved on its own gave chamber 0 setpoints that jumped by up to +0.16 and
    -0.15 kPa from one control tick to the next, down then up (the QP's answer moved between chambers)."""
    import asyncio

    from phantom.model.inverse import Target

    parts, clock = PartsStandIn(False), FakeClock()
    parts.model = ModelInProcess("builtin:calibrated")
    daemon = parts.daemon(clock)
    sent = []

    async def command(name, fields=None):
        if name == "SET_SETPOINTS":
            sent.append(np.asarray(fields["setpoint_pa"], dtype=float) / 1e3)
        return "OK"

    parts.session.command = command
    daemon._feed(daemon.core.board, True)  # the board connected and configured (where Daemon.on_online ends)

    async def play():
        daemon.start_scene(prepare_run({"timeline": {"end_s": 18}, "steps": [
            {"at_s": 0, "volume_ml": 30.0}, {"at_s": 1, "ramp_s": 15, "volume_ml": 35.0}]}, "ramp", CHAMBERS, 1.0))
        for _ in range(180):
            daemon.control_tick()
            for _ in range(5):
                await asyncio.sleep(0)
            clock.now_s += 0.1

    asyncio.run(play())
    setpoints = np.asarray(sent)
    steps = np.diff(setpoints, axis=0)
    assert len(setpoints) > 140                            # a setpoint per tick of the 15 s ramp
    assert steps.min() >= -0.0015, f"a setpoint fell on the way up: {steps.min(axis=0)} kPa"
    assert steps.max() <= 0.015, f"a setpoint jumped: {steps.max(axis=0)} kPa in one tick"
    top = parts.model.worker._worker_pressures_for(Target(gland_volume_m3=35e-6)).pressures_pa / 1e3
    np.testing.assert_allclose(setpoints[-1], np.round(top, 3), atol=0.0015)


@pytest.mark.slow
def test_a_model_worker_killed_like_the_oom_killer_does_is_replaced_and_answers():
    """Before, every later set_target and surface failed with BrokenProcessPool until the daemon restarted."""
    from phantom.host.model_worker import ModelWorker
    from phantom.host.scenes import parse_target

    async def scenario():
        worker = await ModelWorker.start("builtin:calibrated")
        try:
            target = parse_target({"volume_ml": 32.0}, worker.info.chamber_names)
            before = await worker.pressures_for(target)
            for pid in list(worker._pool._processes):
                os.kill(pid, signal.SIGKILL)
            time.sleep(0.5)
            after, again = await asyncio.gather(worker.pressures_for(target), worker.pressures_for(target))
            return before, after, again, worker.restarts
        finally:
            worker.close()

    before, after, again, restarts = asyncio.run(scenario())
    assert restarts == 1                    # two callers found it dead; one replaced it
    np.testing.assert_allclose(after.pressures_pa, before.pressures_pa)
    np.testing.assert_allclose(again.pressures_pa, before.pressures_pa)


@pytest.mark.slow
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGKILL])
def test_a_daemon_stopped_while_it_builds_its_response_table_leaves_no_process(tmp_path, signum):
    """Issue 23, defect 12: SIGTERM during a first start's table build killed the daemon at once; its worker died
    with it (PR_SET_DEATHSIG), but the build's own pool processes were left under PID 1, one spinning, one hung.
    A SIGKILL (the OOM killer, systemd's last resort) left them too, with their pool's semaphores in /dev/shm."""
    from phantom import cache_dir

    cache = tmp_path / "cache"
    cache.mkdir()
    for kind in cache_dir("meshes").parent.iterdir():           # everything cached but the response tables
        if kind.name != "response":
            (cache / kind.name).symlink_to(kind)
    semaphores_before = set(Path("/dev/shm").glob("sem.*"))
    # (the 4-node scene without its table files: the built-in ones ship theirs, so a daemon on them builds none)
    daemon = subprocess.Popen([str(Path(sys.executable).with_name("phantom")), "daemon", "--port",
                               str(tmp_path / "no-board"), "--socket", str(tmp_path / "d.sock"), "--scene",
                               str(calibrated_without_its_table(tmp_path))],
                              env={**os.environ, "PHANTOM_CACHE_DIR": str(cache)}, stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 180
        while not (builders := [pid for pid in descendants(daemon.pid) if pid not in child_pids(daemon.pid)]):
            assert daemon.poll() is None and time.monotonic() < deadline, "no table build started"
            time.sleep(0.2)
        time.sleep(1.0)                                        # the build's pool has made its semaphores
        everyone = descendants(daemon.pid)
        # the new ones that the daemon's processes hold (another test's, made meanwhile, may outlive this one)
        semaphores = _semaphores_mapped_by([daemon.pid, *everyone]) - semaphores_before
        daemon.send_signal(signum)
        assert daemon.wait(30) == (0 if signum == signal.SIGTERM else -signal.SIGKILL)
        deadline = time.monotonic() + 10
        while ((alive := [pid for pid in everyone if _runs(pid)]) or any(path.exists() for path in semaphores)) \
                and time.monotonic() < deadline:
            time.sleep(0.1)
        assert alive == [], f"left running: {alive} (table builders {builders})"
        assert semaphores and not [path for path in semaphores if path.exists()]
    finally:
        if daemon.poll() is None:
            daemon.kill()
            daemon.wait(10)


def _semaphores_mapped_by(pids):
    """The named POSIX semaphores (/dev/shm/sem.*) that any of ``pids`` has mapped, from /proc/PID/maps."""
    found = set()
    for pid in pids:
        try:
            maps = Path(f"/proc/{pid}/maps").read_text()
        except OSError:
            continue
        # address, permissions, offset, device, inode, path (" (deleted)" after one already unlinked)
        paths = (line.split(maxsplit=5)[5] for line in maps.splitlines() if " /dev/shm/sem." in line)
        found.update(Path(path) for path in paths if not path.endswith(" (deleted)"))
    return found


def _runs(pid):
    state = Path(f"/proc/{pid}/stat")
    try:
        return state.read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def test_the_table_builds_progress_is_logged_at_once_and_then_every_report_period(caplog):
    """The log says how far the build is from its first control tick (a build that started with the daemon and a
    session that ends in a few seconds still leave a line saying it ran), then every BUILD_REPORT_S."""
    from types import SimpleNamespace

    from phantom.host.startup import BUILD_REPORT_S

    parts, clock = PartsStandIn(False), FakeClock()
    daemon = parts.daemon(clock)
    daemon.table.build = SimpleNamespace(finished=False,
                                         text=lambda: f"response table solves: {daemon.now_s():.1f} s so far")
    with caplog.at_level(logging.INFO, logger="phantom.host.startup"):
        for _ in range(int(2.5 * BUILD_REPORT_S / 0.5) + 1):  # 2.5 report periods of 0.5 s control ticks
            daemon.table.report_tick(daemon.now_s())
            clock.now_s += 0.5
        logged = [record.getMessage() for record in caplog.records if "response table solves" in record.getMessage()]
    assert [message.split(" (")[0] for message in logged] == [
        f"response table solves: {seconds:.1f} s so far" for seconds in (0.0, BUILD_REPORT_S, 2 * BUILD_REPORT_S)]


def board_frame(board_time_ms: int, setpoints_kpa, kpa=None, fault_flags=0):
    from types import SimpleNamespace

    setpoints = np.asarray(setpoints_kpa, dtype=float) * 1e3
    pressures = setpoints if kpa is None else np.asarray(kpa, dtype=float) * 1e3
    return SimpleNamespace(board_time_ms=board_time_ms, pressures_pa=pressures, setpoints_pa=setpoints,
                           drive_levels=np.zeros(3), states=["REGULATING"] * 3, fault_flags=fault_flags)


@pytest.mark.parametrize("back", ["restarted", "kept", "lost", "no frame"])
def test_a_reconnection_lets_the_boards_first_frame_say_whether_a_reached_target_was_interrupted(monkeypatch, back):
    """The link back after a loss: before the reached target's setpoints go again, the daemon lets the board's
    first frame come, whose clock (gone back: it restarted) or setpoints (not the target's: lost) say whether the
    target was interrupted; a board that kept them interrupted nothing."""
    from test_control_core import HELD_PA, hold, settle, volume

    from phantom.host import daemon as daemon_module
    from phantom.host.session import BoardInfo

    monkeypatch.setattr(daemon_module, "FIRST_FRAME_WAIT_S", 0.2)
    parts, clock = PartsStandIn(False), FakeClock()
    daemon = parts.daemon(clock)
    core, held_kpa = daemon.core, HELD_PA / 1e3
    core.board(clock.now_s, True)
    hold(core, clock.now_s, volume(32.0))
    settle(core, clock.now_s, 1.2 + core.rule.settled_for_s, estimate_ml=32.0)
    assert core._reached == volume(32.0)
    daemon.on_telemetry(board_frame(60_000, held_kpa))                   # up for a minute, holding the target
    clock.now_s += 5.0
    daemon._feed(core.board, False, "the link is disconnected")
    info = BoardInfo(1, 0, "1.0.0", "UNO", 3, "POWER_ON", 0)

    async def reconnect():
        online = asyncio.create_task(daemon.on_online(info, True))
        for _ in range(20):
            await asyncio.sleep(0)
        waited = not online.done()                                       # the first frame is waited for
        if back == "restarted":
            daemon.on_telemetry(board_frame(1_600, [0, 0, 0], [0, 0, 0]))   # its clock went back
        elif back == "kept":
            daemon.on_telemetry(board_frame(66_000, held_kpa))
        elif back == "lost":
            daemon.on_telemetry(board_frame(66_000, [0, 0, 0], [0, 0, 0]))
        await online
        for _ in range(20):                                              # the setpoints sent again, acknowledged
            await asyncio.sleep(0)
        return waited

    assert asyncio.run(reconnect())
    assert ("command", "SET_SETPOINTS") in parts.calls and core.target_applied
    after = {"restarted": "board restart", "lost": "link loss"}.get(back)
    texts = [event["text"] for event in daemon.events]
    if after is None:  # kept, or no frame came: nothing said
        assert core.target_after_interruption is None and not [text for text in texts if "not held" in text]
    else:
        assert core.target_after_interruption == {"state": "settling", "after": after}
        assert status_of(daemon)["target_after_interruption"] == {"state": "settling", "after": after}
        (said,) = [text for text in texts if "not held" in text]
        assert ("the board restarted (its clock went back from 60.0 s to 1.6 s)" in said if back == "restarted"
                else "the board reports setpoints 0.000, 0.000, 0.000 kPa since its link was lost" in said)


def status_of(daemon):
    from phantom.host.status import daemon_status

    return daemon_status(daemon)
