"""The panel's presets: named targets with what each means clinically, and the ``presets`` API method.

The shipped presets are :data:`DEFAULT_PRESETS`; a daemon's config file may give its own as an array of tables
beside its ``[daemon]`` table (each a name, a meaning, and one target as ``phantom set`` takes it)::

    [[presets]]
    name = "symmetric BPH"
    meaning = "benign prostatic hyperplasia: both lobes enlarged evenly"
    volume_ml = 44
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from phantom import PhantomError, read_text
from phantom.host.api import Handler
from phantom.host.scenes import parse_target
from phantom.model.errors import SceneError

if TYPE_CHECKING:
    from phantom.host.daemon import Daemon

#: The shipped example scenes the panel offers to play (host/scenes/).
SCENES_FOLDER = Path(__file__).resolve().parent / "scenes"


class PresetError(PhantomError):
    """A preset of the config file is not a name, a meaning and one target the phantom can take."""


@dataclass(frozen=True)
class Preset:
    """A named target for the panel's buttons.

    Attributes
    ----------
    name : str
        The button's words.
    meaning : str
        What the gland is like, clinically (the button's second line).
    target : dict
        ``set_target``'s params (one of volume_ml, chamber_volumes_ml, pressures_kpa; a growth_ratio).
    """

    name: str
    meaning: str
    target: dict[str, Any]

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "meaning": self.meaning, "target": self.target}


#: The shipped presets. The phantom at rest holds 26.3 ml, so "normal" asks a little more than its rest; the
#: chambers are the base (chamber0), the left lobe (chamber1) and the right lobe (chamber2).
DEFAULT_PRESETS: tuple[Preset, ...] = (
    Preset("normal", "a healthy adult gland, about 20-30 ml: smooth, symmetric, rubbery, the median sulcus felt",
           {"volume_ml": 26.5}),
    Preset("symmetric BPH", "benign prostatic hyperplasia, 44 ml: enlarged evenly, smooth and symmetric; the "
           "median sulcus shallower", {"volume_ml": 44.0}),
    Preset("left lobe enlarged", "asymmetric enlargement of the left lobe, 34 ml: a lopsided gland, which a "
           "clinician notes and follows up", {"volume_ml": 34.0, "growth_ratio": {"chamber1": 3.0, "chamber2": 1.0}}),
    Preset("right lobe enlarged", "asymmetric enlargement of the right lobe, 34 ml: the mirror of the left",
           {"volume_ml": 34.0, "growth_ratio": {"chamber1": 1.0, "chamber2": 3.0}}),
)


def load_presets(path: str | Path) -> tuple[Preset, ...] | None:
    """The ``[[presets]]`` of a daemon's config file, or None when it has none (the shipped ones then stand).
    Their targets are checked against the phantom by :func:`check_presets` once its chambers are known."""
    path = Path(path)
    try:
        raw = tomllib.loads(read_text(path, 2**20, "the config file", PresetError))
    except tomllib.TOMLDecodeError as error:
        raise PresetError(f"the config file {path} is not valid TOML: {error}") from None
    listed = raw.get("presets")
    if listed is None:
        return None
    if not isinstance(listed, list) or not listed or not all(isinstance(item, dict) for item in listed):
        raise PresetError(f"{path}: presets must be an array of tables ([[presets]]), each a name, a meaning and a "
                          "target")
    presets = []
    for index, item in enumerate(listed):
        where = f"{path}: presets[{index}]"
        name, meaning = item.get("name"), item.get("meaning", "")
        if not isinstance(name, str) or not name.strip() or len(name) > 60:
            raise PresetError(f"{where}: name must be a string of 1 to 60 characters, got {name!r:.80}")
        if not isinstance(meaning, str) or len(meaning) > 300:
            raise PresetError(f"{where} ({name}): meaning must be a string of at most 300 characters")
        target = {key: value for key, value in item.items() if key not in ("name", "meaning")}
        presets.append(Preset(name.strip(), meaning, target))
    names = [preset.name for preset in presets]
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise PresetError(f"{path}: presets named more than once: {', '.join(repeated)}")
    return tuple(presets)


def check_presets(presets: tuple[Preset, ...], chamber_names: list[str], chamber_labels: list[str]) -> None:
    """Every preset's target as ``set_target`` would check it; PresetError naming the preset otherwise."""
    for preset in presets:
        try:
            parse_target(dict(preset.target), chamber_names, f"preset {preset.name!r}", chamber_labels)
        except SceneError as error:
            raise PresetError(str(error)) from None


def shipped_scenes() -> list[dict[str, str]]:
    """The example scenes the panel offers: name, absolute path and the first line of its description."""
    scenes = []
    for path in sorted(SCENES_FOLDER.glob("*.toml")):
        first = next((line.lstrip("# ").strip() for line in path.read_text().splitlines() if line.startswith("#")),
                     "")
        scenes.append({"name": path.stem, "path": str(path), "description": first})
    return scenes


def preset_method(daemon: Daemon, presets: tuple[Preset, ...]) -> dict[str, Handler]:
    """The ``presets`` API method: the presets, the shipped scenes, and the gland volumes the phantom can reach
    (at rest, and with every chamber at the model's highest pressure: the volume slider's range)."""
    reachable_ml: list[float] = []

    async def presets_answer(params: dict[str, Any]) -> dict[str, Any]:
        info = daemon.model.info
        if not reachable_ml:
            highest = await daemon.model.estimate(np.full(len(daemon.chamber_names), info.pressure_max_pa))
            reachable_ml[:] = [info.rest_volume_ml, highest.gland_volume_ml]
        return {"presets": [preset.to_json() for preset in presets], "scenes": shipped_scenes(),
                "volume_range_ml": reachable_ml, "pressure_max_kpa": info.pressure_max_pa / 1e3,
                "chamber_labels": daemon.chamber_labels}
    return {"presets": presets_answer}
