"""A scene's gland volume steps beyond the reachable range are refused when it is loaded, before anything moves;
``phantom run-scene --wait`` exits non-zero when the daemon found a step of a scene that ran beyond the phantom's
range (its record's ``unreachable``); ``run_scene``'s time scale is bounded.

Before: a copy of bph_growth with its 30 ml step at 3000 ml played, its step 1 "reached" as 26.52 ml (-99.10 %),
``run-scene --wait`` exited 0 and the daemon's log only warned (a point of the ramp toward 3000 ml each time);
``run_scene`` took ``time_scale: 1e308`` (a wall duration of 2.1e-306 s).

The refusal at load is tested on the daemon with stand-ins for its parts (no model, no board), on the model
worker's real answers (slow), and end to end on ``phantom daemon --sim`` (sim).
"""

import asyncio
import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
from daemon_standins import DaemonStandIns, ModelInProcess, StandInModel, model_info

from phantom.host.api import ApiError
from phantom.host.scenes import example_scene_path, load_timeline_scene
from phantom.model.target import UnreachableTargetError

REPO = Path(__file__).resolve().parent.parent
PHANTOM = Path(sys.executable).with_name("phantom")
#: The range the converged model's unreachable answers state (host/README.md: "give 26.296 to 51.581 ml").
RANGE_ML = (26.296, 51.581)


def bph_with(path: Path, old: str, new: str) -> Path:
    """The shipped BPH growth scene with one line replaced (as the defect's ``sed``)."""
    text = example_scene_path("bph_growth").read_text()
    assert f"\n{old}\n" in text
    path.write_text(text.replace(f"\n{old}\n", f"\n{new}\n"))
    return path


def scene_file(path: Path, steps: list[str], end_s: float) -> Path:
    """A scene of the example scenes' model with these ``[[steps]]`` (TOML bodies)."""
    path.write_text('model = "builtin:converged"\n\n[timeline]\nend_s = ' + f"{end_s}\n\n"
                    + "".join(f"[[steps]]\n{step}\n\n" for step in steps))
    return path


class RangeModel(StandInModel):
    """A model whose inverse refuses gland volumes beyond :data:`RANGE_ML` with that range (as the worker's does)
    and notes each volume it is asked in the stand-ins' ``asked``."""

    async def pressures_for(self, target):
        volume_ml = target.gland_volume_m3 * 1e6
        self.parts.asked.append(volume_ml)
        if not RANGE_ML[0] <= volume_ml <= RANGE_ML[1]:
            raise UnreachableTargetError(f"the gland volume target {volume_ml:.3f} ml is unreachable: "
                                         f"pressures between 0 and [3, 3, 3] kPa give {RANGE_ML[0]} to "
                                         f"{RANGE_ML[1]} ml", RANGE_ML)
        return SimpleNamespace(target=target)


class StandIns(DaemonStandIns):
    """The daemon's parts as stand-ins on the model of ``scene``: the model a :class:`RangeModel`, the board
    noting its commands (``commands``)."""

    model_type = RangeModel

    def __init__(self, scene: Path):
        from phantom.host.scenes import effective_model

        self.asked: list[float] = []
        super().__init__(model_info(RANGE_ML[0], "table", "builtin:converged",
                                    effective_model=effective_model(load_timeline_scene(scene))))

    def handlers(self):
        from phantom.host.handlers import ApiHandlers

        daemon = self.daemon()
        return daemon, ApiHandlers(daemon)


def run_scene(scene: Path, **params):
    """``run_scene`` on a daemon of stand-ins: (its answer or ApiError, the daemon, the stand-ins)."""
    parts = StandIns(scene)
    daemon, handlers = parts.handlers()

    async def call():
        try:
            return await handlers.run_scene({"path": str(scene), **params})
        except ApiError as error:
            return error
    return asyncio.run(call()), daemon, parts


def test_a_volume_step_beyond_the_reachable_range_is_refused_at_load_with_the_step_and_the_range(tmp_path):
    scene = bph_with(tmp_path / "h_vol.toml", "volume_ml = 30", "volume_ml = 3000")
    error, daemon, parts = run_scene(scene, time_scale=50)
    assert isinstance(error, ApiError), error
    assert error.code == "unreachable"  # the code a `set` of an unreachable volume gets
    assert "steps[1] at 20 s asks 3000.00 ml" in str(error) and "26.296 to 51.581 ml" in str(error), error
    assert "the scene was not started" in str(error)
    assert error.data == {"gland_range_ml": list(RANGE_ML), "corrected": False, "step": 1, "at_s": 20.0,
                          "steps": [1]}
    # nothing moved: no scene, no command to the board; the model asked about the highest step only
    assert daemon.scenes.run is None and parts.commands == []
    assert parts.asked == [3000.0]


def test_the_first_step_beyond_the_range_is_named_and_every_one_listed_on_two_asks_of_2000_steps(tmp_path):
    steps = [f"at_s = {index}\nvolume_ml = {30 + (index % 10)}" for index in range(2000)]
    steps[1500] = "at_s = 1500\nvolume_ml = 3000"
    steps[700] = "at_s = 700\nvolume_ml = 60"
    steps[1700] = "at_s = 1700\nvolume_ml = 10"
    error, daemon, parts = run_scene(scene_file(tmp_path / "long.toml", steps, 2010))
    assert isinstance(error, ApiError) and error.code == "unreachable", error
    assert "steps[700] at 700 s asks 60.00 ml" in str(error) and "(so are steps 1500, 1700)" in str(error), error
    assert error.data["steps"] == [700, 1500, 1700] and error.data["step"] == 700
    assert len(parts.asked) == 1 and daemon.scenes.run is None


def test_a_reachable_scene_starts_after_two_asks_whatever_its_length(tmp_path):
    steps = [f"at_s = {index}\nvolume_ml = {30 + (index % 20)}" for index in range(2000)]
    answer, daemon, parts = run_scene(scene_file(tmp_path / "long.toml", steps, 2010), time_scale=10)
    assert not isinstance(answer, ApiError), answer
    assert answer["steps"] == 2000 and daemon.scenes.active
    assert sorted(parts.asked) == [30.0, 49.0]  # the lowest and the highest volume step, nothing else


def test_steps_of_the_other_kinds_are_not_asked_about_at_load(tmp_path):
    scene = scene_file(tmp_path / "pressures.toml", ["at_s = 0\npressures_kpa = [0.0, 1.5, 0.5]",
                                                      "at_s = 10\nchamber_volumes_ml = [2.0, 3.5, 3.5]"], 20)
    answer, daemon, parts = run_scene(scene)
    assert not isinstance(answer, ApiError), answer
    assert parts.asked == [] and daemon.scenes.active


@pytest.mark.parametrize("time_scale", [1e308, 1000.5, 0, -1])
def test_the_time_scale_is_bounded_and_the_bound_said(tmp_path, time_scale):
    error, daemon, _ = run_scene(example_scene_path("bph_growth"), time_scale=time_scale)
    assert isinstance(error, ApiError) and error.code == "invalid_params", error
    assert "time_scale must be above 0 and at most 1000" in str(error), error
    assert daemon.scenes.run is None


def test_the_fastest_time_scale_is_taken():
    answer, _, _ = run_scene(example_scene_path("bph_growth"), time_scale=1000)
    assert not isinstance(answer, ApiError), answer
    assert answer["wall_duration_s"] == pytest.approx(0.21)


# --- phantom run-scene --wait: its exit status -----------------------------------------------------------------

#: The defect's step table (bph_growth with 3000 ml at step 1, at time scale 50).
DEFECT_STEPS = [
    {"index": 0, "at_s": 0.0, "target": "26.50 ml", "target_volume_ml": 26.5, "reached_volume_ml": 26.41,
     "error_pct": -0.34, "reached_after_s": None, "true_volume_ml": 26.43, "unreachable": None},
    {"index": 1, "at_s": 20.0, "target": "chambers 9, -, - ml", "target_volume_ml": None,
     "reached_volume_ml": 26.52, "error_pct": None, "reached_after_s": None, "true_volume_ml": 28.79,
     "unreachable": "target chambers 9, -, - ml is unreachable: base at 9 ml is beyond its 0.0-4.1 ml"},
    {"index": 2, "at_s": 60.0, "target": "35.00 ml", "target_volume_ml": 35.0, "reached_volume_ml": 35.06,
     "error_pct": 0.17, "reached_after_s": 3.2, "true_volume_ml": 34.4, "unreachable": None},
]


def test_the_steps_the_daemon_found_unreachable_are_said_in_one_line():
    """A step the load's range check cannot judge (not a gland volume) and the daemon then found beyond the
    phantom's range: its record's ``unreachable`` says why; a step merely not yet settled (a scene played fast) is
    not a failure."""
    from phantom.cli.client import unreachable_steps

    line = unreachable_steps(DEFECT_STEPS)
    assert line is not None and "\n" not in line
    assert line == ("step 1 (at 20 s): target chambers 9, -, - ml is unreachable: base at 9 ml is beyond its "
                    "0.0-4.1 ml"), line
    assert unreachable_steps([DEFECT_STEPS[0], DEFECT_STEPS[2]]) is None


def cli_run_scene(monkeypatch, capsys, steps, *arguments):
    """``phantom run-scene`` against a stand-in client whose scene finished with ``steps``: (status, out, err)."""
    from phantom.cli import client as cli
    from phantom.cli.main import main
    from phantom.host.client import SceneRun, SceneState, SceneStep

    class Daemon:
        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def run_scene(self, path, time_scale=1.0):
            return SceneRun("h_vol", len(steps), 210.0, 210.0 / time_scale)

        def follow_scene(self, run, on_progress=None):
            return SceneState("h_vol", 210.0, 210.0, 50.0, True, tuple(SceneStep.from_json(step) for step in steps))

    monkeypatch.setattr(cli, "_connect", lambda args, wait_ready=True: Daemon())
    status = main(["run-scene", str(example_scene_path("bph_growth")), "--time-scale", "50", *arguments])
    captured = capsys.readouterr()
    return status, captured.out, captured.err


@pytest.mark.parametrize("json_output", [False, True])
def test_run_scene_wait_exits_1_with_one_line_when_a_step_was_not_reached(monkeypatch, capsys, json_output):
    status, out, err = cli_run_scene(monkeypatch, capsys, DEFECT_STEPS, "--wait", *(["--json"] if json_output else []))
    assert status == 1
    assert ("35.00 ml" in out) if not json_output else len(json.loads(out)) == 3  # the table still printed
    errors = [line for line in err.splitlines() if "error" in line]
    assert len(errors) == 1 and errors[0].startswith("phantom run-scene: error: step 1 (at 20 s): target chambers"), \
        err


def test_run_scene_wait_exits_0_when_every_step_was_reached(monkeypatch, capsys):
    status, _, err = cli_run_scene(monkeypatch, capsys, [DEFECT_STEPS[0], DEFECT_STEPS[2]], "--wait")
    assert status == 0 and "error" not in err, err


# --- the model worker's own range (no board) ----------------------------------------------------------------------

@pytest.mark.slow
def test_the_refusal_states_the_range_the_model_worker_answers_a_set_with(tmp_path, default_model_cached):
    """On the example scenes' model in this process: the range of the refusal is the one a ``set`` of 3000 ml
    is answered with (the worker's), and a reachable scene is taken."""
    from phantom.host import model_worker
    from phantom.model.target import Target

    scene = bph_with(tmp_path / "h_vol.toml", "volume_ml = 30", "volume_ml = 3000")
    parts = StandIns(scene)
    parts.model = ModelInProcess("builtin:converged")
    daemon, handlers = parts.handlers()
    with pytest.raises(UnreachableTargetError) as set_error:
        model_worker._worker_pressures_for(Target(gland_volume_m3=3000e-6))
    with pytest.raises(ApiError) as error:
        asyncio.run(handlers.run_scene({"path": str(scene), "time_scale": 50}))
    assert error.value.code == "unreachable" and "steps[1] at 20 s asks 3000.00 ml" in str(error.value)
    assert error.value.data["gland_range_ml"] == pytest.approx(list(set_error.value.gland_range_ml))
    assert daemon.scenes.run is None and parts.commands == []
    started = asyncio.run(handlers.run_scene({"path": str(example_scene_path("bph_growth")), "time_scale": 50}))
    assert started["steps"] == 5 and daemon.scenes.active


# --- end to end: phantom daemon --sim (simavr) ----------------------------------------------------------------------

@pytest.mark.sim
@pytest.mark.slow
@pytest.mark.timeout(600)
def test_phantom_run_scene_refuses_the_unreachable_scene_and_says_the_steps_not_reached(tmp_path,
                                                                                      default_model_cached):
    from daemon_rig import daemon_process

    from phantom.host.client import DaemonClient

    scene = bph_with(tmp_path / "h_vol.toml", "volume_ml = 30", "volume_ml = 3000")
    with daemon_process(tmp_path, "--sim", "--sim-speed", "2", ready_s=120) as daemon:
        def cli(*arguments):
            return subprocess.run([str(PHANTOM), "run-scene", *arguments, "--socket", str(daemon.socket)],
                                  capture_output=True, text=True, timeout=120)

        refused = cli(str(scene), "--time-scale", "50", "--wait")
        assert refused.returncode == 2, refused.stderr + daemon.log()
        assert "steps[1] at 20 s asks 3000.00 ml" in refused.stderr and "26.296 to 51.581 ml" in refused.stderr
        with DaemonClient(daemon.socket) as client:
            status = client.call("status")
        assert status["scene"] is None and status["control"] != "scene", status
        # a scene that is taken and played far faster than the pressures settle: nothing was beyond the range
        fast = cli("bph_growth", "--time-scale", "1000", "--wait")
        assert fast.returncode == 0, fast.stdout + fast.stderr + daemon.log()
        too_fast = cli("bph_growth", "--time-scale", "1e308")
        assert too_fast.returncode == 2 and "at most 1000" in too_fast.stderr, too_fast.stderr
