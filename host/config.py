"""The daemon's settings, defined once: :class:`DaemonConfig`.

Every field says its type (its annotation), its default, and in its metadata a :class:`Setting`: the help
people read and the range a value must lie in. From these come

* the keys of the config file's ``[daemon]`` table (:func:`load_config`; e.g. /etc/phantom/phantomd.toml),
  each checked for its type and range when the file loads;
* the ``phantom daemon`` flags (phantom/cli/daemon.py builds them with :func:`settings`: ``mesh_hz`` is
  ``--mesh-hz``, a switch like ``vent_on_exit`` is ``--vent-on-exit`` / ``--no-vent-on-exit``).

Flags win over the file. The settings of a group (the board, the recording) exclude each other: a group given
by a flag replaces the file's, and :data:`GROUPS` says whether a daemon needs one.

This module imports nothing heavy: the command line builds its parser from it at every start.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
import types
import typing
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from phantom import PhantomError, read_text

#: The metadata key under which a field keeps its :class:`Setting`.
SETTING = "setting"

#: The largest config file read (bytes): the shipped one is under 3 KiB.
MAX_CONFIG_BYTES = 2**20

#: Groups of settings that exclude each other (at most one of a group is given), and whether one is required.
GROUPS: dict[str, bool] = {"board": True, "recording": False}


class ConfigError(PhantomError):
    """A setting of the daemon has the wrong type or lies outside its range, or a config file is unusable."""


@dataclass(frozen=True)
class Setting:
    """What people are told about one setting, and the range its value must lie in.

    Attributes
    ----------
    help : str
        One sentence (the flag's help; the config file's comment).
    metavar : str
        The value's name in ``--help`` (e.g. ``DEV``, ``HZ``); switches have none.
    at_least, above, at_most : float, optional
        The range of a number: ``value >= at_least``, ``value > above``, ``value <= at_most``.
    group : str, optional
        A key of :data:`GROUPS`: the settings of one group exclude each other.
    choices : tuple of str
        The words a text setting may be (empty: any text).
    """

    help: str
    metavar: str = ""
    at_least: float | None = None
    above: float | None = None
    at_most: float | None = None
    group: str | None = None
    choices: tuple[str, ...] = ()

    def range_text(self) -> str:
        """The range in words, e.g. ``between 50 and 10000``, ``> 0``, ``one of ideal, real``; empty without one."""
        if self.choices:
            return f"one of {', '.join(self.choices)}"
        low = f">= {self.at_least:g}" if self.at_least is not None else (
            f"> {self.above:g}" if self.above is not None else "")
        if self.at_most is None:
            return low
        if self.at_least is not None:
            return f"between {self.at_least:g} and {self.at_most:g}"
        return f"{low} and <= {self.at_most:g}" if low else f"<= {self.at_most:g}"

    def contains(self, value: float) -> bool:
        """Whether a (finite) number lies in the range."""
        return ((self.at_least is None or value >= self.at_least) and (self.above is None or value > self.above)
                and (self.at_most is None or value <= self.at_most))


def setting(default: Any, help: str, **limits: Any) -> Any:
    """A dataclass field with a default and a :class:`Setting` (``limits``: its other attributes)."""
    return field(default=default, metadata={SETTING: Setting(help, **limits)})


@dataclass(frozen=True)
class DaemonConfig:
    """Everything ``phantom daemon`` is told, by its flags or the ``[daemon]`` table of its config file.

    Built with a value out of range, or without exactly one board, it raises :class:`ConfigError`.
    """

    port: str | None = setting(None, "the board's serial port (e.g. /dev/serial/by-id/usb-...)", metavar="DEV",
                               group="board")
    sim: bool = setting(False, "start the simulated board (the real firmware in simavr) and drive it", group="board")
    can_channel: str | None = setting(None, "talk to the board over CAN on this channel", metavar="CH",
                                      group="board")
    baud: int = setting(115200, "serial baud rate", metavar="N", above=0)
    boot_delay_s: float | None = setting(
        None, "with a serial port: stay silent this long (s) after opening it, while the board's bootloader runs; "
        "unset: 2 s, enough for the Uno's Optiboot and the Mega's stk500v2; 0 for an adapter without DTR",
        metavar="S",
        at_least=0, at_most=60)
    can_interface: str = setting("socketcan", "python-can interface", metavar="NAME")
    sim_speed: float = setting(1.0, "simulated board speed-up: 1 real time, 0 as fast as it can", metavar="X",
                               at_least=0, at_most=100)
    scene: str = setting("builtin:converged", "scene: 'builtin:converged' (the calibrated, converged phantom), "
                         "'builtin:calibrated' (its coarse 4-node fit), 'builtin' or a TOML path",
                         metavar="S")
    run_scene: bool = setting(False, "play the scene's [[steps]] as soon as the daemon is ready")
    phantom: str = setting("default", "the phantom's name: its measured volumes (`phantom corrections --phantom NAME`, "
                           "in the user's data directory) correct the model's answers", metavar="NAME")
    socket: Path | None = setting(
        None, "the API's Unix socket (default: $PHANTOM_SOCKET, /run/phantom/phantomd.sock, "
        "$XDG_RUNTIME_DIR/phantomd.sock or /tmp/phantomd-UID/phantomd.sock)", metavar="PATH")
    rerun_save: Path | None = setting(None, "record to this .rrd file (its folder is created)", metavar="FILE",
                                      group="recording")
    rerun_connect: str | None = setting(None, "stream to a Rerun viewer (rerun+http://.../proxy)", metavar="ADDR",
                                        group="recording")
    camera: str | None = setting(None, "the scanner's camera for scans and verified targets on a real board: a V4L2 "
                                 "device number (0: /dev/video0) or a stream's URL (MJPEG over HTTP, RTSP); needs "
                                 "--rig", metavar="DEVICE|URL")
    rig: Path | None = setting(None, "the scanner's rig calibration (rig.json from phantom scan calibrate) for "
                               "--camera", metavar="RIG.json")
    look: str = setting("ideal", "with --sim: the virtual camera's pictures, for scans and verified targets: ideal (an "
                        "even backdrop, the phantom floating in view) or real (hung by its tubes, glossy, an uneven "
                        "cloth, vignetting)", metavar="LOOK", choices=("ideal", "real"))
    mesh_hz: float = setting(1.0, "rate (Hz) of deformed-mesh logging while recording a scene with [outputs] "
                             "shape = true; 0: none; at most the control rate", metavar="HZ", at_least=0,
                             at_most=10)
    host_deadline_ms: int = setting(500, "the board's dead-host deadline (ms): it stops the blowers when the daemon "
                                    "falls silent this long (wall clock: a simulated board's counts at its speed)",
                                    metavar="MS", at_least=50, at_most=10000)
    telemetry_period_ms: int = setting(20, "the board's telemetry period (ms)", metavar="MS", at_least=10,
                                       at_most=1000)
    link_rt_priority: int = setting(10, "the SCHED_FIFO priority the board link's process asks for, so that its "
                                    "keepalive runs before a busy machine's other work (root, CAP_SYS_NICE or an "
                                    "RLIMIT_RTPRIO this high: the systemd unit's LimitRTPRIO=); refused, it runs "
                                    "at the daemon's priority; 0: do not ask", metavar="N", at_least=0, at_most=99)
    kp_per_kpa: float = setting(4.0, "the board's PID proportional gain (drive level per kPa), sent to every chamber "
                                "with SET_PID at each connection", metavar="K", at_least=0, at_most=100)
    ki_per_kpa_s: float = setting(15.0, "the board's PID integral gain (drive level per kPa s)", metavar="K",
                                  at_least=0, at_most=1000)
    kd_s_per_kpa: float = setting(0.0, "the board's PID derivative gain (drive level per kPa/s)", metavar="K",
                                  at_least=0, at_most=1)
    pressure_limit_kpa: float = setting(4.0, "the board's over-pressure limit per chamber (kPa): a chamber above it "
                                        "latches OVERPRESSURE; at least the scene's pressure_max_kpa", metavar="KPA",
                                        above=0, at_most=6)
    settled_kpa: float = setting(0.1, "a target is reached once every chamber's pressure has stayed within this of "
                                 "its setpoint (kPa) for --settled-for-s and the estimate is within the target's "
                                 "tolerance", metavar="KPA", above=0, at_most=1)
    settled_for_s: float = setting(1.0, "how long the pressures must stay settled for a target to be reached (s)",
                                   metavar="S", at_least=0, at_most=60)
    http: str | None = setting(None, "serve the browser panel and the API over a WebSocket at HOST:PORT (e.g. "
                               "127.0.0.1:8080; a port alone is 127.0.0.1's, this machine only; off unless given): "
                               "host/web.py", metavar="HOST:PORT")
    http_token: bool = setting(True, "ask every panel connection for its token (panel-tokens.json in the user's data "
                               "directory); --no-http-token is refused unless --http is a loopback address")
    http_hosts: str | None = setting(None, "host names (comma-separated) the panel may be reached by besides IP "
                                     "addresses and localhost, e.g. the lab PC's name: other Host headers are "
                                     "refused (DNS rebinding)", metavar="NAMES")
    vent_on_exit: bool = setting(True, "vent the phantom when the daemon stops")
    zero_on_connect: bool = setting(True, "zero the pressure sensors (ZERO_SENSORS) after connecting when the "
                                    "phantom is vented")

    def __post_init__(self) -> None:
        for name, value in dataclasses.asdict(self).items():
            object.__setattr__(self, name, checked(name, value, name))
        for group, required in GROUPS.items():
            members = [item for item in settings() if item.setting.group == group]
            given = sum(1 for item in members if getattr(self, item.name))
            if given > 1 or (required and not given):
                raise ConfigError(f"give {'exactly' if required else 'at most'} one {group}: "
                                  + ", ".join(item.flag_usage for item in members[:-1])
                                  + f", or {members[-1].flag_usage}")


@dataclass(frozen=True)
class SettingField:
    """One setting as the command line and the config file see it: name, value type, default and Setting."""

    name: str
    kind: type
    optional: bool
    default: Any
    setting: Setting

    @property
    def flag(self) -> str:
        """The ``phantom daemon`` flag, e.g. ``--mesh-hz``."""
        return "--" + self.name.replace("_", "-")

    @property
    def flag_usage(self) -> str:
        """The flag as usage shows it, e.g. ``--port DEV``."""
        return f"{self.flag} {self.setting.metavar}" if self.setting.metavar else self.flag


def settings() -> Iterator[SettingField]:
    """Every setting of :class:`DaemonConfig`, in its order."""
    hints = typing.get_type_hints(DaemonConfig)
    for item in dataclasses.fields(DaemonConfig):
        kinds = typing.get_args(hints[item.name]) if isinstance(hints[item.name], types.UnionType) else (
            hints[item.name],)
        kind = next(k for k in kinds if k is not type(None))
        yield SettingField(item.name, kind, type(None) in kinds, item.default, item.metadata[SETTING])


def _by_name() -> dict[str, SettingField]:
    return {item.name: item for item in settings()}


def checked(name: str, value: Any, where: str) -> Any:
    """``value`` as setting ``name`` holds it (a TOML or JSON value: ints for floats, strings for paths), or a
    ConfigError that starts with ``where`` and says what was wrong."""
    item = _by_name()[name]
    if value is None:
        if item.optional:
            return None
        raise ConfigError(f"{where} needs a value")
    if item.kind is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where} must be true or false, got {value!r}")
        return value
    if item.kind is Path:
        if not isinstance(value, (str, Path)) or not str(value):
            raise ConfigError(f"{where} must be a path, got {value!r}")
        return Path(value)
    if item.kind is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where} must be a string, got {value!r}")
        if item.setting.choices and value not in item.setting.choices:
            raise ConfigError(f"{where} must be {item.setting.range_text()}, got {value!r}")
        return value
    numbers = (int,) if item.kind is int else (int, float)
    if isinstance(value, bool) or not isinstance(value, numbers):
        raise ConfigError(f"{where} must be {'an integer' if item.kind is int else 'a number'}, got {value!r}")
    number = item.kind(value)
    if not math.isfinite(number) or not item.setting.contains(number):
        raise ConfigError(f"{where} must be {item.setting.range_text() or 'finite'}, got {value!r}")
    return number


def load_config(path: str | Path) -> dict[str, Any]:
    """The ``[daemon]`` table of a config file, each value checked and converted (see :func:`checked`).

    Raises ConfigError naming the file and the key: a missing or unreadable file, bad TOML, an unknown key, a
    value of the wrong type or out of range.
    """
    path = Path(path)
    text = read_text(path, MAX_CONFIG_BYTES, "the config file", ConfigError)
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(f"the config file {path} is not valid TOML: {error}") from None
    except RecursionError:
        raise ConfigError(f"the config file {path} is not valid TOML: it nests too deeply") from None
    table = raw.get("daemon", {})
    if not isinstance(table, dict):
        raise ConfigError(f"{path}: daemon must be a table ([daemon])")
    known = _by_name()
    unknown = sorted(set(table) - set(known))
    if unknown:
        raise ConfigError(f"{path}: unknown key(s) in [daemon]: {', '.join(unknown)}; known: {', '.join(known)}")
    return {key: checked(key, value, f"{path}: [daemon] {key}") for key, value in table.items()}


def merged_config(file_values: Mapping[str, Any], flag_values: Mapping[str, Any]) -> DaemonConfig:
    """The config from a config file's values and the flags given (None: not given), flags winning; a group
    given by a flag replaces the file's settings of that group."""
    by_name = _by_name()
    given = {name: value for name, value in flag_values.items() if value is not None}
    flagged_groups = {by_name[name].setting.group for name in given} - {None}
    values = {name: value for name, value in file_values.items() if by_name[name].setting.group not in flagged_groups}
    values.update(given)
    return DaemonConfig(**values)
