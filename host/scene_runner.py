"""Playing a scene's ``[[steps]]`` timeline: which target is in force now, and how each step went.

The runner reads the time from an injected clock (``time.monotonic`` in the daemon, a plain counter in the
tests), so that its rules are tested without waiting: a step starts when the scene's time (wall time since
the start times the time scale) passes its ``at_s``; a step is reached when the control core says so
(host/control.py, its one rule, once the step's ramp has ended); the last estimate before the next step is the
volume it reached; at ``end_s`` the run finishes and its last target holds.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from phantom import is_finite_number
from phantom.host.scenes import MAX_SCENE_S, Timeline, gland_volume_ml, parse_timeline
from phantom.host.verify import Verify
from phantom.model.errors import SceneError
from phantom.model.target import Target

#: What the runner tells people: ``(kind, text, level)``, level INFO, WARN or ERROR.
EventSink = Callable[[str, str, str], None]


@dataclass
class StepRecord:
    """How one scene step went: when it started (clock s), its target volume (ml), when the estimate reached it."""

    index: int
    at_s: float
    target: str
    target_volume_ml: float | None
    started_clock_s: float
    reached_after_s: float | None = None
    final_volume_ml: float | None = None
    true_volume_ml: float | None = None
    #: when (s after the step's start) the board first acknowledged setpoints for this step; None: not yet
    applied_after_s: float | None = None
    #: why its target (or a point of its ramp) could not be reached: beyond the phantom's range; None: it could
    unreachable: str | None = None

    def to_json(self) -> dict[str, Any]:
        error_pct = None
        if self.target_volume_ml and self.final_volume_ml is not None:
            error_pct = 100.0 * (self.final_volume_ml - self.target_volume_ml) / self.target_volume_ml
        return {"index": self.index, "at_s": self.at_s, "target": self.target,
                "target_volume_ml": self.target_volume_ml, "reached_volume_ml": self.final_volume_ml,
                "error_pct": error_pct, "reached_after_s": self.reached_after_s,
                "true_volume_ml": self.true_volume_ml, "applied_after_s": self.applied_after_s,
                "unreachable": self.unreachable}


@dataclass
class SceneRun:
    """A scene timeline being played: its clock origin and the record of its steps."""

    name: str
    timeline: Timeline
    end_s: float
    time_scale: float
    started_clock_s: float
    wants_shape: bool = False
    steps: list[StepRecord] = field(default_factory=list)
    #: it played to its end, or was stopped before it (``stopped``)
    finished: bool = False
    #: why it was stopped before its end (a new target, vent); None: it was not
    stopped: str | None = None
    #: since when (clock s) the scene's clock waits (a step being scanned, or the scene stopped); None: it runs
    held_since_s: float | None = None

    def scene_time_s(self, clock_s: float) -> float:
        """Seconds of scene time at clock reading ``clock_s`` (s); the time held (a scan) does not count."""
        if self.held_since_s is not None:
            clock_s = min(clock_s, self.held_since_s)
        return (clock_s - self.started_clock_s) * self.time_scale

    def to_json(self, clock_s: float) -> dict[str, Any]:
        return {"name": self.name, "time_s": min(self.scene_time_s(clock_s), self.end_s), "end_s": self.end_s,
                "time_scale": self.time_scale, "finished": self.finished, "stopped": self.stopped,
                "steps": [step.to_json() for step in self.steps]}


@dataclass(frozen=True)
class PreparedRun:
    """A scene's timeline checked and ready to play (:func:`prepare_run`)."""

    name: str
    timeline: Timeline
    end_s: float
    time_scale: float
    wants_shape: bool


def prepare_run(raw: dict[str, Any], name: str, chamber_names: list[str], time_scale: float,
                wants_shape: bool = False) -> PreparedRun:
    """Check a scene's ``[[steps]]`` and ``[timeline]`` against the chambers; raises SceneError naming what is
    wrong. Pure (no clock, no event): the daemon runs it off its event loop."""
    timeline = parse_timeline(raw.get("steps"), chamber_names, name)
    if not timeline.steps:
        raise SceneError(f"{name} has no [[steps]]: nothing to run")
    settings = raw.get("timeline", {})
    end_s = settings.get("end_s", timeline.duration_s + 10.0) if isinstance(settings, dict) else None
    if not is_finite_number(end_s) or not timeline.duration_s <= end_s <= MAX_SCENE_S:
        raise SceneError(f"{name}: [timeline] end_s must be a number from {timeline.duration_s:g} s (the end of the "
                         f"last step's ramp) to {MAX_SCENE_S:g} s (a week), got {end_s!r:.40}")
    if not is_finite_number(time_scale) or time_scale <= 0:
        raise SceneError(f"time_scale must be a positive number, got {time_scale!r:.40}")
    return PreparedRun(name, timeline, float(end_s), float(time_scale), wants_shape)


class SceneRunner:
    """Plays one scene at a time against a clock; :meth:`tick` says which target is in force.

    Parameters
    ----------
    clock : callable() -> float
        Seconds, monotonic (``time.monotonic`` in the daemon).
    on_event : callable(kind, text, level)
        Where step starts, the end and stops are reported.
    """

    def __init__(self, clock: Callable[[], float], on_event: EventSink):
        self.clock = clock
        self.on_event = on_event
        self.run: SceneRun | None = None

    @property
    def active(self) -> bool:
        """Whether a scene is playing (started and not finished or stopped)."""
        return self.run is not None and not self.run.finished

    def scene_time_s(self) -> float | None:
        """The playing scene's time (s), or None when none plays."""
        return min(self.run.scene_time_s(self.clock()), self.run.end_s) if self.active and self.run else None

    def start(self, raw: dict[str, Any], name: str, chamber_names: list[str], time_scale: float,
              wants_shape: bool = False) -> dict[str, Any]:
        """Check a scene's ``[[steps]]`` and ``[timeline]`` against the chambers and start playing it
        (:func:`prepare_run`, then :meth:`begin`); raises SceneError naming what is wrong."""
        return self.begin(prepare_run(raw, name, chamber_names, time_scale, wants_shape))

    def begin(self, prepared: PreparedRun) -> dict[str, Any]:
        """Start playing a checked scene (replacing the one playing); returns ``name``, ``steps``, ``end_s``,
        ``time_scale``, ``wall_duration_s``."""
        if self.active and self.run is not None:
            self.stop(f"replaced by {prepared.name}")
        self.run = SceneRun(prepared.name, prepared.timeline, prepared.end_s, prepared.time_scale, self.clock(),
                            prepared.wants_shape)
        self.on_event("scene", f"scene {prepared.name} started: {len(prepared.timeline.steps)} steps over "
                      f"{prepared.end_s:g} s (time scale {prepared.time_scale:g})", "INFO")
        return {"name": prepared.name, "steps": len(prepared.timeline.steps), "end_s": prepared.end_s,
                "time_scale": prepared.time_scale, "wall_duration_s": prepared.end_s / prepared.time_scale}

    def stop(self, why: str) -> None:
        """Stop the playing scene (a new target, vent); its record stays for ``status``."""
        if self.active and self.run is not None:
            self.run.finished, self.run.stopped = True, why
            if self.run.held_since_s is None:          # its time stands where it stopped
                self.run.held_since_s = self.clock()
            self.on_event("scene", f"scene {self.run.name} stopped: {why}", "INFO")

    def tick(self) -> Target | None:
        """Advance to the clock's time: record the steps that started, finish at the end.

        Returns the target in force (interpolated along a ramp), or None before the first step, after the end
        or when no scene plays.
        """
        run = self.run
        if run is None or run.finished:
            return None
        now_s = self.clock()
        scene_time_s = run.scene_time_s(now_s)
        index = run.timeline.step_index_at(scene_time_s)
        if index is not None:
            for new_index in range(len(run.steps), index + 1):
                step = run.timeline.steps[new_index]
                volume_ml = gland_volume_ml(step.target)
                # the step's own start on the clock, not the tick that noticed it (up to a control period later)
                started_s = run.started_clock_s + step.at_s / run.time_scale
                run.steps.append(StepRecord(new_index, step.at_s, step.target.describe(), volume_ml, started_s))
                self.on_event("scene", f"step {new_index} at {step.at_s:g} s: {step.target.describe()}"
                              + (f" over {step.ramp_s:g} s" if step.ramp_s else ""), "INFO")
        if scene_time_s >= run.end_s:
            run.finished = True
            self.on_event("scene", f"scene {run.name} finished; holding its last target", "INFO")
            return None
        return run.timeline.target_at(scene_time_s)

    def hold(self, held: bool) -> None:
        """The scene's clock waits while ``held`` (a step's scan, host/control.py); it goes on from where it
        stopped when released."""
        run = self.run
        if run is None or run.finished or held == (run.held_since_s is not None):
            return
        now_s = self.clock()
        if held:
            run.held_since_s = now_s
        else:
            assert run.held_since_s is not None
            run.started_clock_s += now_s - run.held_since_s
            run.held_since_s = None

    def verify(self) -> Verify | None:
        """How the step in force is verified by the scanner (None: it is not)."""
        run = self.run
        if run is None or run.finished or not run.steps:
            return None
        return run.timeline.steps[run.steps[-1].index].verify

    def step_index(self) -> int | None:
        """The index of the step in force (the last one started), or None when no scene plays or none started."""
        run = self.run
        return None if run is None or run.finished or not run.steps else run.steps[-1].index

    def ramp(self) -> tuple[Target, Target] | None:
        """The two targets the playing scene's ramp moves between now, or None outside a ramp."""
        run = self.run
        if run is None or run.finished:
            return None
        return run.timeline.ramp_at(run.scene_time_s(self.clock()))

    def applied(self, index: int) -> None:
        """The board acknowledged setpoints for step ``index``: the first time is the step's ``applied_after_s``."""
        run = self.run
        if run is None or index >= len(run.steps) or run.steps[index].applied_after_s is not None:
            return
        record = run.steps[index]
        record.applied_after_s = max(0.0, self.clock() - record.started_clock_s)

    def reached(self, index: int) -> None:
        """Step ``index`` was reached (the control core's rule): the first time is its ``reached_after_s``."""
        run = self.run
        if run is None or index >= len(run.steps) or run.steps[index].reached_after_s is not None:
            return
        record = run.steps[index]
        record.reached_after_s = max(0.0, self.clock() - record.started_clock_s)

    def unreachable(self, index: int, text: str) -> None:
        """Step ``index``'s target (or a point of its ramp) is beyond the phantom's range: the first ``text`` is
        its ``unreachable``."""
        run = self.run
        if run is None or index >= len(run.steps) or run.steps[index].unreachable is not None:
            return
        run.steps[index].unreachable = text

    def observe(self, estimated_volume_ml: float, predicted_volume_ml: float | None = None,
                solved_target: Target | None = None, true_volume_ml: float | None = None) -> None:
        """Book an estimate against the current step: its latest volume (and the simulated plant's true one,
        when known). A step without a volume target (pressures, chamber volumes) takes the inverse's
        ``predicted_volume_ml`` for its own ``solved_target``."""
        run = self.run
        if run is None or not run.steps:
            return
        record = run.steps[-1]
        if run.finished and record.final_volume_ml is not None:
            return
        record.final_volume_ml = estimated_volume_ml
        record.true_volume_ml = true_volume_ml
        step = run.timeline.steps[record.index]
        if record.target_volume_ml is None and predicted_volume_ml is not None and solved_target == step.target:
            record.target_volume_ml = predicted_volume_ml

    def to_json(self) -> dict[str, Any] | None:
        """The run for ``status`` (None when no scene was started)."""
        return self.run.to_json(self.clock()) if self.run is not None else None
