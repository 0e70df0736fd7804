"""Scene timelines: the ``[[steps]]`` of a scene file as targets over time, with holds and ramps; and timeline
scenes that name their model.

A timeline scene names the model it plays on, ``model = "builtin:converged"`` (or the path of a whole scene,
taken from the scene's folder), and carries only what differs from it on purpose (``[outputs] shape = true``),
besides its ``[timeline]`` and ``[[steps]]``: :func:`read_timeline_scene` lays its tables over the model's,
key by key, and lists what it overrides (``phantom daemon`` says so when it starts). Recalibrating the model
edits no timeline. A whole scene (``[phantom]``, ``[material]``, ...) with steps still loads as it is.

A step starts at ``at_s`` (seconds from the start of the run) with exactly one target form:
``volume_ml`` (the gland's total volume, optionally with ``growth_ratio``), ``chamber_volumes_ml`` (one
per chamber) or ``pressures_kpa`` (raw pressures, one per chamber). With ``ramp_s`` > 0 the target moves
linearly from the previous step's over ``ramp_s`` seconds; it then holds until the next step starts. A
``volume_ml`` step may be verified by the scanner once reached: ``verify = "scan"`` (optionally
``verify_tolerance_pct``, ``verify_rounds``: scanned and corrected until within, as ``set_target``'s verify) or
``scan = true`` (one scan recorded and stored as a measurement, no second round); the scene's clock waits
while a step scans. A step may instead give a gland to look like, ``shape = "patient.nii.gz"`` (a mask or closed
mesh, taken from the scene's folder; optionally ``labels`` and ``refine_solves``): the daemon's ``run_scene``
solves it by the shape inverse before the scene starts and plays it as the pressures it answers
(:func:`shape_steps`, :func:`with_shape_pressures`).
"""

from __future__ import annotations

import bisect
import dataclasses
import functools
import math
import numbers
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from phantom import is_finite_number
from phantom.host.verify import MAX_VERIFY_ROUNDS, VERIFY_TOLERANCE_PCT, Verify
from phantom.model.errors import SceneError
from phantom.model.scene import (
    BUILTIN_SCENES,
    Scene,
    builtin_scene_path,
    chamber_labels_of,
    describe_chambers,
    pressure_limit_error,
    read_scene_toml,
    scene_from_dict,
)
from phantom.model.target import Target

#: A target's keys as a scene's step or the API's ``set_target`` states it (the units people see), each with the
#: inverse's target kind (:data:`phantom.model.target.TARGET_KINDS`).
TARGET_KEYS: dict[str, str] = {"volume_ml": "volume", "chamber_volumes_ml": "chamber_volumes",
                               "pressures_kpa": "pressures"}

ML_PER_M3 = 1e6
PA_PER_KPA = 1e3
#: The smallest volume a target may ask for (ml): far below any phantom's, and far above the tiny numbers (5e-324)
#: that vanish in SI units and divided by zero in the inverse.
MIN_VOLUME_ML = 1e-3
#: The most steps a timeline may have: a step every 2 s for over an hour. A 20,000-step scene took 0.57 s to
#: check, time the daemon's loop cannot give at once.
MAX_STEPS = 2000
#: The latest a step may start and end its ramp (s of scene time): a week, far beyond a session at the bench or a
#: night's endurance run (the shipped scenes last minutes), and far below 1e300 s, which was taken and made a
#: scene without ``[timeline] end_s`` run for ever.
MAX_SCENE_S = 7 * 24 * 3600.0
#: The fastest ``run_scene`` plays a timeline (times faster than written): a week's timeline (:data:`MAX_SCENE_S`)
#: in about ten minutes. Faster, a scene's steps last less than the daemon's control period (0.1 s); 1e308 was
#: taken and answered a wall duration of 2e-306 s.
MAX_TIME_SCALE = 1000.0


#: A ``[[steps]]`` table header at the start of a line of TOML text.
_STEP_HEADER = re.compile(r"^[ \t]*\[\[[ \t]*steps[ \t]*\]\]", re.MULTILINE)


def check_step_count(text: str, name: str) -> None:
    """Refuse a scene whose text has more than :data:`MAX_STEPS` ``[[steps]]`` headers before it is parsed: a
    20,000-step file, under the size limit, took tomllib 0.3-0.5 s of pure Python in a worker thread, holding the
    GIL that the daemon's loop and the link's loop need (stalls of 56 and 72 ms). :func:`parse_timeline` counts
    the steps of a parsed scene, however they were written."""
    _check_steps(len(_STEP_HEADER.findall(text)), name)


def _check_steps(count: int, name: str) -> None:
    if count > MAX_STEPS:
        raise SceneError(f"{name} has {count} steps; a scene may have at most {MAX_STEPS}: split it into several "
                         "scenes")


def _to_si(key: str, value: float) -> float:
    """A number of a target key (ml or kPa) in SI units (m^3 or Pa)."""
    return value * PA_PER_KPA if key == "pressures_kpa" else value / ML_PER_M3


def gland_volume_ml(target: Target) -> float | None:
    """The gland volume (ml) a volume target asks for, as people stated it; None for the other kinds."""
    return target.to_json()["volume_ml"] if target.kind == "volume" else None


@dataclass(frozen=True)
class Step:
    """One timeline step: from ``at_s`` (s) the target moves to ``target`` over ``ramp_s`` (s), then holds."""

    at_s: float
    target: Target
    ramp_s: float = 0.0
    #: ``verify = "scan"`` (or ``scan = true``: one scan recorded, no correction) once reached (host/control.py)
    verify: Verify | None = None


@dataclass
class Timeline:
    """An ordered list of steps, with the target at any time of the run.

    Attributes
    ----------
    steps : list of Step
        Sorted by ``at_s``; the first starts at 0 s or later (before it there is no target).
    name : str
        Where the timeline came from (a scene path), for messages.
    """

    steps: list[Step] = field(default_factory=list)
    name: str = "timeline"

    @property
    def duration_s(self) -> float:
        """The time (s) at which the last step has finished ramping."""
        if not self.steps:
            return 0.0
        return max(step.at_s + step.ramp_s for step in self.steps)

    @functools.cached_property
    def starts_s(self) -> list[float]:
        """Each step's ``at_s`` (s), in order."""
        return [step.at_s for step in self.steps]

    def step_index_at(self, time_s: float) -> int | None:
        """Index of the step in force at ``time_s`` (s), or None before the first."""
        index = bisect.bisect_right(self.starts_s, time_s) - 1
        return index if index >= 0 else None

    def ramp_at(self, time_s: float) -> tuple[Target, Target] | None:
        """The two targets a ramp at ``time_s`` (s) moves between (the previous step's and its own), or None when
        no step ramps then."""
        index = self.step_index_at(time_s)
        if index is None or index == 0:
            return None
        step = self.steps[index]
        if step.ramp_s <= 0 or time_s >= step.at_s + step.ramp_s:
            return None
        return self.steps[index - 1].target, step.target

    def target_at(self, time_s: float) -> Target | None:
        """The target at ``time_s`` (s): the step in force, linearly interpolated while it ramps.

        During a ramp of step k from ``at_s`` over ``ramp_s`` the values are
        ``previous + (time_s - at_s) / ramp_s * (target - previous)``.
        """
        index = self.step_index_at(time_s)
        if index is None:
            return None
        step = self.steps[index]
        if step.ramp_s <= 0 or index == 0 or time_s >= step.at_s + step.ramp_s:
            return step.target
        previous = self.steps[index - 1].target
        fraction = (time_s - step.at_s) / step.ramp_s
        values = tuple(
            None if new is None or old is None else old + fraction * (new - old)
            for old, new in zip(previous.values, step.target.values, strict=True)
        )
        return Target.of_kind(step.target.kind, values, step.target.growth_ratio)


def finite_number(value: object, what: str) -> float:
    """A finite float from a TOML/JSON value, or a SceneError naming ``what``: the check of a target's numbers
    (``set_target``, ``surface``, a scene's steps), a step's times and ``run_scene``'s time scale (also bounded
    by :func:`time_scale_of`)."""
    if is_finite_number(value):
        return float(value)
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise SceneError(f"{what} must be a number, got {value!r}")
    if isinstance(value, numbers.Integral):  # JSON and TOML allow an integer of any length; a float holds ~1.8e308
        digits = math.floor(int(value).bit_length() * math.log10(2)) + 1
        raise SceneError(f"{what} must be a finite number (at most about 1.8e308), got an integer of about {digits} "
                         "digits")
    raise SceneError(f"{what} must be finite, got {value!r}")


def time_scale_of(value: object, what: str = "run_scene: time_scale") -> float:
    """``run_scene``'s time scale: a number above 0 and at most :data:`MAX_TIME_SCALE`; SceneError naming the
    bound."""
    time_scale = finite_number(value, what)
    if not 0.0 < time_scale <= MAX_TIME_SCALE:
        raise SceneError(f"{what} must be above 0 and at most {MAX_TIME_SCALE:g} (times faster than the scene is "
                         f"written: a week's timeline in about {MAX_SCENE_S / MAX_TIME_SCALE / 60:.0f} minutes), got "
                         f"{time_scale:g}")
    return time_scale


def parse_target(raw: dict[str, Any], chamber_names: list[str], where: str = "target",
                 chamber_labels: Sequence[str] | None = None) -> Target:
    """Check and convert one target given as a dict (a scene step or the API's ``set_target`` params).

    Parameters
    ----------
    raw : dict
        Exactly one of ``volume_ml`` (ml, > 0), ``chamber_volumes_ml`` (list of ml or None, one per chamber),
        ``pressures_kpa`` (list of kPa >= 0, one per chamber); optional ``growth_ratio`` (with ``volume_ml``
        only: a table from chamber name, or chamber index, to a weight > 0).
    chamber_names : list of str
        The phantom's chambers, in order: lengths and growth-ratio keys are checked against them.
    where : str
        Names the target in error messages (e.g. ``"steps[2]"``).
    chamber_labels : list of str, optional
        How messages name the chambers (``phantom status``'s names; default: the scene's default labels).
    """
    if not isinstance(raw, dict):
        raise SceneError(f"{where}: a target must be a table/object, got {type(raw).__name__}")
    if "shape" in raw:
        raise SceneError(f"{where}: a shape step is solved when the daemon is asked to run the scene (phantom "
                         "run-scene SCENE): start the daemon on the scene's model, then run it")
    # a misspelt key first: else "volum_ml = 30" was told that no target key was given
    unknown = set(raw) - set(TARGET_KEYS) - {"growth_ratio", "at_s", "ramp_s"}
    if unknown:
        raise SceneError(f"{where}: unknown key(s) {', '.join(repr(key) for key in sorted(unknown))}: a target gives "
                         f"exactly one of {', '.join(TARGET_KEYS)} (growth_ratio with volume_ml)")
    keys = [key for key in TARGET_KEYS if key in raw]
    if len(keys) != 1:
        raise SceneError(
            f"{where}: give exactly one of {', '.join(TARGET_KEYS)}; got "
            f"{', '.join(keys) if keys else 'none'}")
    kind = keys[0]
    n_chambers = len(chamber_names)
    labels = list(chamber_labels) if chamber_labels is not None else chamber_labels_of({}, chamber_names)
    if kind == "volume_ml":
        volume_ml = finite_number(raw[kind], f"{where}: volume_ml")
        if volume_ml < MIN_VOLUME_ML:
            raise SceneError(f"{where}: volume_ml must be positive (at least {MIN_VOLUME_ML:g} ml), got {volume_ml:g}")
        values: tuple[float | None, ...] = (volume_ml,)
    else:
        listed = raw[kind]
        if not isinstance(listed, (list, tuple)) or len(listed) != n_chambers:
            raise SceneError(f"{where}: {kind} must be a list of {n_chambers} numbers (one per chamber: "
                             f"{describe_chambers(labels)}), got {listed!r}")
        if kind == "pressures_kpa":
            pressures = [finite_number(value, f"{where}: pressures_kpa[{i}]") for i, value in enumerate(listed)]
            refused = pressure_limit_error(pressures, labels)  # the upper limit is the model's: the inverse's
            if refused:
                raise SceneError(f"{where}: {refused}")
            values = tuple(pressures)
        else:
            values = tuple(None if value is None else finite_number(value, f"{where}: chamber_volumes_ml[{i}]")
                           for i, value in enumerate(listed))
            if all(value is None for value in values):
                raise SceneError(f"{where}: chamber_volumes_ml needs at least one number")
            if any(value is not None and value < MIN_VOLUME_ML for value in values):
                raise SceneError(f"{where}: chamber_volumes_ml must be positive (at least {MIN_VOLUME_ML:g} ml "
                                 f"each), got {list(values)}")
    growth_ratio = _parse_growth_ratio(raw.get("growth_ratio"), kind, chamber_names, where)
    return Target.of_kind(TARGET_KEYS[kind], [None if value is None else _to_si(kind, value) for value in values],
                          growth_ratio)


def _parse_growth_ratio(raw: Any, kind: str, chamber_names: list[str], where: str) -> dict[int, float] | None:
    """The growth ratio as chamber index -> weight; keys are chamber names or indices."""
    if raw is None:
        return None
    if kind != "volume_ml":
        raise SceneError(f"{where}: growth_ratio goes with volume_ml only")
    if not isinstance(raw, dict) or not raw:
        raise SceneError(f"{where}: growth_ratio must be a table like {{ chamber1 = 2.0, chamber2 = 1.0 }}")
    ratio: dict[int, float] = {}
    for key, weight in raw.items():
        if key in chamber_names:
            index = chamber_names.index(key)
        elif str(key).isascii() and str(key).isdigit() and int(key) < len(chamber_names):
            index = int(key)
        else:
            raise SceneError(f"{where}: growth_ratio names unknown chamber {key!r}; chambers are "
                             f"{', '.join(chamber_names)}")
        weight = finite_number(weight, f"{where}: growth_ratio[{key}]")
        if weight <= 0:
            raise SceneError(f"{where}: growth_ratio weights must be positive, got {key} = {weight:g}")
        ratio[index] = weight
    return ratio


def shape_steps(raw_steps: object, scene_folder: Path) -> list[tuple[int, dict[str, Any]]]:
    """The steps of a ``[[steps]]`` list that give a ``shape``, each with its shape's keys (``shape`` resolved
    from ``scene_folder`` when it is a relative path), in order; the others are left to :func:`parse_timeline`."""
    found = []
    for index, raw in enumerate(raw_steps if isinstance(raw_steps, list) else []):
        if isinstance(raw, dict) and "shape" in raw:
            keys = {key: value for key, value in raw.items() if key not in ("at_s", "ramp_s")}
            if isinstance(keys["shape"], str) and keys["shape"]:
                keys["shape"] = str(scene_folder / Path(keys["shape"]).expanduser())
            found.append((index, keys))
    return found


def with_shape_pressures(raw: dict[str, Any], pressures_kpa: dict[int, list[float]]) -> dict[str, Any]:
    """The scene's tables with each shape step (index -> the shape inverse's pressures, kPa) played as those
    pressures: ``shape``, ``labels`` and ``refine_solves`` replaced by ``pressures_kpa``."""
    steps = list(raw.get("steps") or [])
    for index, pressures in pressures_kpa.items():
        kept = {key: value for key, value in steps[index].items() if key not in ("shape", "labels", "refine_solves")}
        steps[index] = {**kept, "pressures_kpa": list(pressures)}
    return {**raw, "steps": steps}


def parse_timeline(raw_steps: object, chamber_names: list[str], name: str = "timeline") -> Timeline:
    """Check and convert a scene's ``[[steps]]`` list into a :class:`Timeline`.

    Steps must be in increasing ``at_s`` (s, >= 0); a step with ``ramp_s`` (s, >= 0) > 0 must follow a
    step of the same target form (a ramp interpolates between two targets of one kind) and end before the
    next step starts.
    """
    if raw_steps is None:
        return Timeline([], name)
    if not isinstance(raw_steps, list):
        raise SceneError(f"{name}: steps must be an array of tables ([[steps]])")
    _check_steps(len(raw_steps), name)
    steps: list[Step] = []
    for position, raw in enumerate(raw_steps):
        where = f"{name}: steps[{position}]"
        if not isinstance(raw, dict) or "at_s" not in raw:
            raise SceneError(f"{where}: every step needs at_s (its start time in seconds)")
        at_s = finite_number(raw["at_s"], f"{where}: at_s")
        ramp_s = finite_number(raw.get("ramp_s", 0.0), f"{where}: ramp_s")
        if at_s < 0 or ramp_s < 0 or at_s + ramp_s > MAX_SCENE_S:
            raise SceneError(f"{where}: at_s and ramp_s must be >= 0 and the step's ramp end by {MAX_SCENE_S:g} s "
                             f"(a week, the longest scene), got at_s={at_s:g}, ramp_s={ramp_s:g}")
        verify = parse_step_verify(raw, where)
        target = parse_target({key: value for key, value in raw.items() if key not in STEP_VERIFY_KEYS},
                              chamber_names, where)
        if verify is not None and target.gland_volume_m3 is None:
            raise SceneError(f"{where}: verify and scan compare the scanned gland volume with the step's: give "
                             "volume_ml")
        if steps:
            previous = steps[-1]
            if at_s <= previous.at_s:
                raise SceneError(f"{where}: at_s={at_s:g} must be later than the previous step's {previous.at_s:g}")
            if previous.at_s + previous.ramp_s > at_s:
                raise SceneError(f"{name}: steps[{position - 1}] ramps until {previous.at_s + previous.ramp_s:g} s, "
                                 f"after steps[{position}] starts at {at_s:g} s")
        if ramp_s > 0:
            if not steps:
                raise SceneError(f"{where}: the first step cannot ramp (there is nothing to ramp from)")
            previous_target = steps[-1].target
            if previous_target.kind != target.kind:
                raise SceneError(f"{where}: a ramp needs the previous step to have the same target form "
                                 f"({previous_target.kind} -> {target.kind})")
            if previous_target.free_chambers != target.free_chambers:
                raise SceneError(f"{where}: a chamber-volume ramp needs the same free chambers in both steps")
        steps.append(Step(at_s, target, ramp_s, verify))
    return Timeline(steps, name)


#: A step's keys of the scanner: ``verify = "scan"`` (with ``verify_tolerance_pct``, ``verify_rounds``) or
#: ``scan = true``.
STEP_VERIFY_KEYS = ("verify", "verify_tolerance_pct", "verify_rounds", "scan")


def parse_step_verify(raw: dict[str, Any], where: str) -> Verify | None:
    """A step's ``verify = "scan"`` or ``"auto"`` (its tolerance and rounds bounded as the API's) or ``scan =
    true``; None without either; SceneError naming what is wrong."""
    verify, scan = raw.get("verify"), raw.get("scan", False)
    tolerance_pct, rounds = raw.get("verify_tolerance_pct"), raw.get("verify_rounds")
    if not isinstance(scan, bool):
        raise SceneError(f"{where}: scan must be true or false, got {scan!r:.60}")
    if verify is None:
        if tolerance_pct is not None or rounds is not None:
            raise SceneError(f"{where}: verify_tolerance_pct and verify_rounds go with verify = \"scan\"")
        return Verify(rounds=1, correct=False) if scan else None
    if scan:
        raise SceneError(f"{where}: give verify = \"scan\" (scan, correct until within the tolerance) or scan = "
                         "true (one scan recorded, no correction), not both")
    if verify not in ("scan", "auto"):
        raise SceneError(f"{where}: verify must be \"scan\" or \"auto\" (a scan only when the correction's 95 % band "
                         f"at the target is wider than the tolerance), got {verify!r:.60}")
    default = Verify()
    tolerance_pct = default.tolerance_pct if tolerance_pct is None else tolerance_pct
    low, high = VERIFY_TOLERANCE_PCT
    if isinstance(tolerance_pct, bool) or not isinstance(tolerance_pct, int | float) or not (
            low <= tolerance_pct <= high):
        raise SceneError(f"{where}: verify_tolerance_pct must be a number from {low:g} to {high:g} (%), got "
                         f"{tolerance_pct!r:.60}")
    rounds = default.rounds if rounds is None else rounds
    if isinstance(rounds, bool) or not isinstance(rounds, int) or not 1 <= rounds <= MAX_VERIFY_ROUNDS:
        raise SceneError(f"{where}: verify_rounds must be a whole number from 1 to {MAX_VERIFY_ROUNDS}, got "
                         f"{rounds!r:.60}")
    return Verify(float(tolerance_pct), rounds, auto=verify == "auto")


def example_scene_path(name: str) -> Path:
    """The path of a shipped example scene (``host/scenes/<name>.toml``)."""
    path = Path(__file__).resolve().parent / "scenes" / f"{name}.toml"
    if not path.is_file():
        shipped = sorted(p.stem for p in path.parent.glob("*.toml"))
        raise SceneError(f"no example scene {name!r}; shipped: {', '.join(shipped)}")
    return path


def effective_model(scene: Any, fidelity: str | None = None, pressure_max_kpa: float | None = None) -> dict[str, Any]:
    """What a scene's timeline runs on, as comparable values: the phantom (mesh, units, chambers, fixed group),
    the built-in prostate's geometry (chambers and mesh size; None for a mesh file), the material (every
    parameter, defaults filled in) and the model settings (fidelity, pressure limit).

    For a running model, ``fidelity`` and ``pressure_max_kpa`` are the ones in force; for a scene file they
    are what it asks for (None: no fidelity named, which any level satisfies).
    """
    settings = scene.model_settings
    if fidelity is None:
        fidelity = settings.fidelity
    if pressure_max_kpa is None:
        pressure_max_kpa = settings.pressure_max_pa / 1e3
    material = scene.material
    material = dataclasses.asdict(material) if dataclasses.is_dataclass(material) and not isinstance(
        material, type) else dict(vars(material))
    geometry = getattr(scene, "geometry", None)
    return {"phantom": {"mesh": scene.mesh, "units": scene.units, "chambers": list(scene.chambers),
                        "fixed": scene.fixed},
            "geometry": geometry.as_table() if geometry is not None else None,
            "material": material,
            "model": {"fidelity": fidelity, "pressure_max_kpa": float(pressure_max_kpa)}}


def model_differences(running: dict[str, Any], candidate: dict[str, Any]) -> list[str]:
    """The tables (``phantom``, ``geometry``, ``material``, ``model``) in which a scene's effective model differs
    from the running one's; a scene that names no fidelity accepts the running one."""
    differing = [table for table in ("phantom", "geometry", "material") if running[table] != candidate[table]]
    wanted_fidelity = candidate["model"]["fidelity"]
    if (wanted_fidelity is not None and wanted_fidelity != running["model"]["fidelity"]) or not math.isclose(
            running["model"]["pressure_max_kpa"], candidate["model"]["pressure_max_kpa"], rel_tol=1e-9):
        differing.append("model")
    return differing


#: The tables of a timeline scene that are its own, not laid over its model's.
TIMELINE_TABLES = ("model", "timeline", "steps")


@dataclass(frozen=True)
class TimelineScene:
    """A scene as the daemon plays it: ``scene`` (the model with what the file overrides, its steps and
    timeline), ``model`` (what the file's ``model =`` names; None for a whole scene) and ``overrides`` (each
    value the file sets that differs from its model's, ``outputs.shape = true (the model's: false)``)."""

    scene: Scene
    model: str | None
    overrides: list[str]

    def describe(self, source: str) -> str:
        """What the daemon's start line says of the scene."""
        if self.model is None:
            return f"the scene {source} (a whole scene: its own model)"
        said = "; it overrides " + ", ".join(self.overrides) if self.overrides else ", overriding nothing"
        return f"the scene {source} on its model {self.model}{said}"


def read_timeline_scene(source: str | Path, raw: dict[str, Any] | None = None) -> TimelineScene:
    """Read a scene for the daemon: a built-in name, a whole scene file, or a timeline scene naming its model
    (module docstring); ``raw``: the file's TOML when it was already read (:func:`read_scene_toml`). Raises
    SceneError naming what is wrong."""
    name = str(source)
    if name in BUILTIN_SCENES:
        path = builtin_scene_path(name)
        return TimelineScene(scene_from_dict(read_scene_toml(path), path), None, [])
    path = Path(name)
    if raw is None:
        raw = read_scene_toml(path)
    named = raw.get("model")
    if not isinstance(named, str):
        return TimelineScene(scene_from_dict(raw, path), None, [])
    model_path = builtin_scene_path(named) if named in BUILTIN_SCENES else (path.parent / named).resolve()
    model_raw = read_scene_toml(model_path)
    if isinstance(model_raw.get("model"), str):
        raise SceneError(f"{path}: its model {named} names a model itself; name a whole scene (builtin:converged, "
                         "or a file with [phantom] and [material])")
    overrides: list[str] = []
    merged = _laid_over(model_raw, {key: value for key, value in raw.items() if key != "model"}, "", overrides)
    try:
        scene = scene_from_dict(merged, model_path)
    except SceneError as error:
        raise SceneError(f"{path} on its model {named}: {error}") from error
    return TimelineScene(dataclasses.replace(scene, path=path), named, overrides)


def _laid_over(model: dict[str, Any], scene: dict[str, Any], prefix: str, overrides: list[str]) -> dict[str, Any]:
    """``scene``'s tables laid over ``model``'s, key by key; each value that differs goes to ``overrides``."""
    merged = dict(model)
    for key, value in scene.items():
        dotted = f"{prefix}{key}"
        old = model.get(key)
        if isinstance(value, dict) and isinstance(old, dict):
            merged[key] = _laid_over(old, value, f"{dotted}.", overrides)
            continue
        merged[key] = value
        if not prefix and key in TIMELINE_TABLES:
            continue
        if old != value:
            overrides.append(f"{dotted} = {_toml_value(value)} (the model's: "
                             f"{'unset' if key not in model else _toml_value(old)})")
    return merged


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return repr(value).replace("'", '"')


def load_timeline_scene(source: str | Path) -> Scene:
    """:func:`read_timeline_scene`'s scene."""
    return read_timeline_scene(source).scene
