"""A simulated board: the real firmware image in simavr, wired to the pneumatic plant, on a pseudo-terminal.

>>> with SimulatedBoard(speed=1.0) as board:           # doctest: +SKIP
...     link = serial.Serial(board.port, 115200)        # opens like /dev/ttyACM0
...     board.inject("sensor_cut", chamber=1)
...     board.plant_state()["pressures_pa"]
"""

from __future__ import annotations

import contextlib
import ctypes
import math
import os
import select
import struct
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from phantom import PhantomError, is_finite_number, process_temporary_folder
from phantom.hil.firmware import ensure_firmware, function_addresses, mcu_of, stock_bootloader
from phantom.hil.harness import HarnessProcess
from phantom.hil.plant import load_plant

#: Firmware functions timed by the cycle counter: role -> (demangled name or its start, min cycles). A call
#: shorter than min cycles is an early return (no telemetry frame due: its prologue and epilogue alone take a
#: few hundred cycles, more if an interrupt hits) and is counted apart; a frame takes several thousand. The
#: control tick covers the three sensors, the safety checks, the PIDs, the steppers' planning and the telemetry
#: frame when one is due.
PROFILED_FUNCTIONS = {
    "control_tick": ("core::Controller::tick(", 0),
    "telemetry_frame": ("core::Controller::send_telemetry(", 1500),
    "receive": ("core::Controller::receive(", 0),
}
#: Interrupt vectors also counted as busy time (vector numbers differ between the two MCUs).
PROFILED_VECTORS = {
    "atmega328p": {"adc_isr": 21, "tick_isr": 14, "step_isr": 15, "uart_rx_isr": 18, "uart_tx_isr": 19,
                   "watchdog_isr": 6},
    "atmega2560": {"adc_isr": 29, "tick_isr": 21, "step_isr": 22, "uart_rx_isr": 25, "uart_tx_isr": 26,
                   "watchdog_isr": 12},
}

#: The harness's SCHED_FIFO priority while paced (``SimulatedBoard(rt_priority=...)``): the simulated board stands
#: in for hardware, which never waits for a core. On a loaded machine a harness at normal priority waited for one
#: for up to 0.4 s at a time (its own session, hence its own autogroup: the other processes' nice values do not
#: reach it); a wait of a second is a board silent for a second, which a daemon driving it as a real board takes
#: for a lost link: it reconnects, stays silent meanwhile (the boot delay) and the board latches DEAD_HOST
#: (tests/test_real_rig_sim.py in make test, twice in five runs). Below the board link's (``LINK_RT_PRIORITY``,
#: 10, phantom.host.link_process), so that the host's keepalive never waits for the simulator. Granted to root or
#: with an RLIMIT_RTPRIO; otherwise the harness runs at normal priority and ``scheduling`` says why. Never asked
#: unpaced (speed 0: it runs flat out), and given up for good by a harness that cannot keep up at its speed
#: (it slept under a tenth of 0.2 s of wall clock: hil/harness/main.c, the real-time guard).
HARNESS_RT_PRIORITY = 5

#: Faults and their parameters (unit in the name) with defaults.
FAULTS: dict[str, dict[str, float]] = {
    "sensor_cut": {},
    "tube_off": {},
    "supply": {"volts": 4.0},
    "leak": {"conductance_ml_per_s_per_kpa": 5.0},
    "stuck_blower": {"level": 1.0},
    "line_noise": {"flip_probability": 0.01, "drop_probability": 0.01},
    "drop_frame": {"message_id": 0, "count": 1},
    "clear": {},
}
_PER_CHAMBER = {"sensor_cut", "tube_off", "leak", "stuck_blower"}


#: inotify's event bit for an open of the watched file (linux/inotify.h).
_IN_OPEN = 0x20


def _event_masks(events: bytes) -> Iterator[int]:
    """The mask of each ``struct inotify_event`` in what one read of an inotify descriptor gave (each: wd, mask,
    cookie, len, then len bytes of name, none for a watched file)."""
    offset = 0
    while offset + 16 <= len(events):
        _, mask, _, name_length = struct.unpack_from("iIII", events, offset)
        yield mask
        offset += 16 + name_length


class SimulationError(PhantomError):
    """A simulated board was used wrongly (bad fault, not started ...)."""


def _profiled_regions(elf: Path, mcu: str) -> dict[str, tuple[int, int]]:
    """Entry address and min cycles of each timed function found in the image."""
    addresses = function_addresses(elf)
    regions = {}
    for role, (prefix, min_cycles) in PROFILED_FUNCTIONS.items():
        found = [address for name, address in addresses.items() if name.startswith(prefix)]
        if found:
            regions[role] = (found[0], min_cycles)
    for role, vector in PROFILED_VECTORS[mcu].items():
        name = f"__vector_{vector}"
        # an unused vector is an alias of __bad_interrupt: nothing to time
        if name in addresses and addresses[name] != addresses.get("__bad_interrupt"):
            regions[role] = (addresses[name], 0)
    return regions


class SimulatedBoard:
    """The firmware image running in simavr against the plant, reachable at ``.port`` like a real board.

    Parameters
    ----------
    elf
        Firmware image; default ``firmware/build/uno-bench/phantom.elf``, built with ``make -C firmware`` if missing.
    plant
        Plant parameter file; default ``hil/plant.toml``.
    speed
        1.0 paces simulated time to the wall clock; > 1 runs faster than real time; 0 as fast as possible.
    seed
        Seed of the sensor noise and the line noise, so a run can be repeated.
    bootloader
        False (the default): the image starts at address 0, as on a board flashed over ISP. True: the MCU's
        stock Arduino bootloader (Optiboot 4.4 on the Uno, stk500v2 on the Mega, from arduino-core-avr) is
        flashed too and the board starts through it, as a stock board does. A path: that .hex instead.
    rt_priority
        The harness's SCHED_FIFO priority while paced (default :data:`HARNESS_RT_PRIORITY`; None: normal
        priority); refused without the right, and never at speed 0. ``scheduling`` says what it runs at.
    """

    def __init__(self, elf: str | Path | None = None, plant: str | Path | None = None, speed: float = 1.0,
                 seed: int = 0, bootloader: bool | str | Path = False,
                 rt_priority: int | None = HARNESS_RT_PRIORITY):
        if not (isinstance(speed, (int, float)) and math.isfinite(speed) and speed >= 0):
            raise SimulationError(
                f"speed must be a number >= 0 (1 = real time, 0 = as fast as possible), got {speed!r}"
            )
        self.elf = ensure_firmware(elf)
        self.plant = load_plant(plant)
        self.speed = float(speed)
        self.seed = int(seed)
        if bootloader is True:
            bootloader = stock_bootloader(mcu_of(self.elf))
        elif bootloader is not False and not Path(bootloader).is_file():
            raise SimulationError(f"the bootloader image {bootloader} does not exist")
        self.bootloader = None if bootloader is False else Path(bootloader)
        if rt_priority is not None and not (isinstance(rt_priority, int) and 1 <= rt_priority <= 99):
            raise SimulationError(f"rt_priority must be a SCHED_FIFO priority, 1 to 99, or None, got {rt_priority!r}")
        self.rt_priority = rt_priority
        #: what the harness runs at ("SCHED_FIFO 5", or "normal (...)" saying why), once started
        self.scheduling: str | None = None
        self._directory: tempfile.TemporaryDirectory[str] | None = None
        self._harness: HarnessProcess | None = None

    @property
    def port(self) -> str:
        """Stable path of the board's serial port (a symlink to the current pseudo-terminal)."""
        if self._directory is None:
            raise SimulationError("the simulated board is not started: use it as a context manager or call start()")
        return str(Path(self._directory.name) / "ttySIM0")

    def start(self) -> SimulatedBoard:
        """Start the harness; the port exists when this returns."""
        if self._harness is not None:
            return self
        directory = self._directory = process_temporary_folder("phantom-sim-")
        mcu = mcu_of(self.elf)
        arguments = ["--elf", str(self.elf), "--mcu", mcu, "--link", self.port]
        arguments += ["--speed", repr(self.speed), "--seed", str(self.seed)]
        if self.bootloader is not None:
            arguments += ["--bootloader", str(self.bootloader)]
        if self.rt_priority is not None and self.speed > 0:
            arguments += ["--rt-priority", str(self.rt_priority)]
        for role, (address, min_cycles) in _profiled_regions(self.elf, mcu).items():
            arguments += ["--profile", f"{role}={address:#x}:{min_cycles}"]
        try:
            self._harness = HarnessProcess(arguments + self.plant.harness_arguments())
        except BaseException:
            directory.cleanup()
            self._directory = None
            raise
        self.scheduling = self._harness.ready.get("scheduling")
        return self

    def stop(self) -> None:
        """Stop the harness and remove the port."""
        if self._harness is not None:
            self._harness.close()
            self._harness = None
        if self._directory is not None:
            self._directory.cleanup()
            self._directory = None

    def __enter__(self) -> SimulatedBoard:
        return self.start()

    def __exit__(self, *exc_info: object) -> None:
        self.stop()

    def _command(self, line: str) -> dict[str, Any]:
        if self._harness is None:
            raise SimulationError("the simulated board is not started: use it as a context manager or call start()")
        return self._harness.command(line)

    def unplug(self) -> None:
        """Pull the USB cable: the port disappears and the board loses power (the blowers stop)."""
        self._command("unplug")

    def replug(self) -> None:
        """Plug it back: the port returns at the same path and the board starts from a power-on reset."""
        self._command("replug")

    def reset(self, cause: str = "external") -> float:
        """Reset the MCU without cutting power: ``"external"`` pulls RESET low as the USB-serial chip's DTR line
        does when a port opens (the bootloader, if any, then waits for an upload), ``"power"`` as a power cycle.
        Returns the simulated time (s) of the reset."""
        if cause not in ("external", "power"):
            raise SimulationError(f"reset cause must be 'external' or 'power', got {cause!r}")
        return float(self._command(f"reset {cause}")["time_s"])

    @contextlib.contextmanager
    def resetting_on_open(self) -> Iterator[list[float]]:
        """Within the block, each open of the port resets the MCU (``"external"``), as the DTR line of a real
        board's USB-serial chip does when a program opens its port; yields the simulated times of the resets so
        far (a list that grows).

        This is how an upload reaches the stock bootloader however late avrdude starts. After a reset, the stock
        bootloaders listen for about a second (the application starts 0.8 s after it on the Mega, 1.0 s on the
        Uno), and avrdude takes about half of that from its start to its first byte: a reset made before ``make
        upload`` started was spent before avrdude sent anything in a loaded ``make test``. A pty has no DTR line,
        so the open itself, seen by inotify, is the signal."""
        port = os.path.realpath(self.port)  # the pty itself; refused if the board is not started
        libc = ctypes.CDLL(None, use_errno=True)
        watch = libc.inotify_init1(os.O_NONBLOCK | os.O_CLOEXEC)
        if watch < 0:
            raise SimulationError(f"cannot watch the port for opens: {os.strerror(ctypes.get_errno())}")
        stop_read, stop_write = os.pipe()
        resets: list[float] = []
        failures: list[BaseException] = []

        def reset_at_each_open() -> None:
            while True:
                ready, _, _ = select.select([watch, stop_read], [], [])
                if stop_read in ready:
                    return
                if any(mask & _IN_OPEN for mask in _event_masks(os.read(watch, 4096))):
                    try:
                        resets.append(self.reset("external"))
                    except BaseException as error:  # raised in the caller's thread at the block's end
                        failures.append(error)
                        return

        try:
            if libc.inotify_add_watch(watch, port.encode(), _IN_OPEN) < 0:
                raise SimulationError(f"cannot watch the port {self.port} for opens: "
                                      f"{os.strerror(ctypes.get_errno())}")
            resetter = threading.Thread(target=reset_at_each_open, name="dtr-on-open", daemon=True)
            resetter.start()
            try:
                yield resets
            finally:
                os.write(stop_write, b"x")
                resetter.join()
        finally:
            for fd in (watch, stop_read, stop_write):
                os.close(fd)
        if failures:
            raise failures[0]

    def inject(self, fault: str, chamber: int | None = None, **params: float) -> float:
        """Inject a fault into the plant or the serial line.

        Parameters
        ----------
        fault
            ``"sensor_cut"`` (the chamber's sensor reads 0 V), ``"tube_off"`` (the sensor's tube came off: it
            reads the room's pressure while the chamber inflates), ``"supply"`` (the board's 5 V rail, AVcc and
            the sensors' supply, at ``volts`` in [2, 5.5], default 4.0), ``"leak"`` (extra leak of
            ``conductance_ml_per_s_per_kpa``, default 5), ``"stuck_blower"`` (the chamber's blower runs at
            ``level`` in [0, 1] whatever the firmware commands, default 1), ``"line_noise"`` (each byte in
            either direction is dropped with ``drop_probability`` and has one bit flipped with
            ``flip_probability``, defaults 0.01), ``"drop_frame"`` (the board's next ``count`` frames, default 1,
            whose message id is ``message_id`` (``MsgId.MOTION_INFO``: no default) are lost whole on their way to
            the host, as a frame whose CRC fails is), ``"clear"`` (remove every injected fault).
            A silent host needs no injection: the host just stops sending.
        chamber
            0, 1 or 2 for the per-chamber faults; must be None for the others.

        Returns
        -------
        float
            The simulated time (s) at which the fault took effect.
        """
        if fault not in FAULTS:
            raise SimulationError(f"unknown fault {fault!r}: choose one of {', '.join(FAULTS)}")
        unknown = sorted(set(params) - set(FAULTS[fault]))
        if unknown:
            raise SimulationError(f"fault {fault!r} takes {sorted(FAULTS[fault]) or 'no parameters'}, not {unknown}")
        if fault in _PER_CHAMBER:
            if chamber not in (0, 1, 2):
                raise SimulationError(f"fault {fault!r} needs chamber=0, 1 or 2, got {chamber!r}")
        elif chamber is not None:
            raise SimulationError(f"fault {fault!r} applies to the whole board: leave chamber=None")
        values = {**FAULTS[fault], **params}
        for name, value in values.items():
            if not is_finite_number(value):
                raise SimulationError(f"{fault}.{name} must be a number, got {value!r}")
            low, limit = (2.0, 5.5) if name == "volts" else (0, 1.0 if name in ("level", "flip_probability",
                                                                                  "drop_probability") else math.inf)
            if not low <= value <= limit:
                raise SimulationError(f"{fault}.{name} must be in [{low:g}, {limit:g}], got {value!r}")
        if fault == "drop_frame":
            if not (float(values["message_id"]).is_integer() and 1 <= values["message_id"] <= 255
                    and float(values["count"]).is_integer() and 1 <= values["count"] <= 1000):
                raise SimulationError(f"drop_frame needs message_id=<a message id, 1 to 255> (MsgId.MOTION_INFO) and "
                                      f"count=<1 to 1000 frames>, got {values}")
            line = f"fault drop_frame {int(values['message_id'])} {int(values['count'])}"
        elif fault == "leak":
            line = f"fault leak {chamber} {values['conductance_ml_per_s_per_kpa'] * 1e-9!r}"
        elif fault == "stuck_blower":
            line = f"fault stuck_blower {chamber} {float(values['level'])!r}"
        elif fault == "line_noise":
            line = f"fault line_noise {float(values['flip_probability'])!r} {float(values['drop_probability'])!r}"
        elif fault == "supply":
            line = f"fault supply {float(values['volts'])!r}"
        elif fault in ("sensor_cut", "tube_off"):
            line = f"fault {fault} {chamber}"
        else:
            line = "fault clear"
        return float(self._command(line)["time_s"])

    def plant_state(self) -> dict[str, Any]:
        """The plant now: time_s, pressures_pa, drive_levels (what the firmware's PWM commands, [0, 1]),
        chamber_volumes_ml, plus effective_drive_levels (after a stuck blower), sensor_voltages_v, powered,
        resets (MCU resets seen, e.g. by the watchdog), max_lag_s (the longest stall behind the wall clock),
        lost_s (wall-clock time the simulation could not keep up with, in total), blower_pins (each blower pin's
        mode: "floating", "pullup", "low", "high" or "pwm"), reset_s (when the core last started from its reset
        vector), control_since_s (when the control tick first ran after that, None before),
        floating_before_control_s (how long a blower pin floated in between) and driven_before_control
        (whether a blower pin was driven high or by PWM in between); lags (the last stalls of the harness behind
        the clock over 50 ms, each [time of day s, board time s, stall s]), host_gaps (the last gaps of over
        0.25 s of board time between the host's bytes to the UART, each [time of day s, board time s at its end,
        gap s, wall-clock s the harness gave up meanwhile, bytes then queued for the UART]: a gap with nothing
        given up is a host that sent nothing), scheduling (what the harness runs at: ``rt_priority``), cpu_s (the
        harness's CPU time since it started); motion, one entry per stepper axis as its
        driver turned it (steps, angle_deg: None until the mechanism's steps per turn are set, enabled); and
        gland_volume_ml, the truth model's gland volume at these pressures, when the plant has a truth table."""
        state = self._command("state")
        gland_volume_ml = self.plant.truth_gland_volume_ml(state["pressures_pa"])
        if gland_volume_ml is not None:
            state["gland_volume_ml"] = gland_volume_ml
        return state

    def motion(self, command: str = "") -> dict[str, Any]:
        """Send ``motion [COMMAND]`` to the harness: the stepper axes as the simulated drivers see them
        (``phantom.hil.motion`` wraps it)."""
        return self._command(f"motion {command}".strip())

    def cycle_stats(self, reset: bool = False) -> dict[str, Any]:
        """CPU cost of the firmware, counted exactly in simavr cycles since start (or the last reset).

        Returns control_tick_cycles_mean/_max and control_ticks, telemetry_frame_cycles_mean/_max and
        telemetry_frames (None when the firmware has no such function), elapsed_cycles, frequency_hz,
        cpu_use_fraction (cycles inside any timed function or interrupt handler, counted once when they nest,
        over elapsed cycles), stack_bytes_max (the stack's deepest point, bytes below the top of RAM), regions
        (every timed function's calls, total and max cycles), serial (byte counters of the line) and simulator_steps
        (the harness's steps: instructions, or jumps to the next event while the core sleeps).
        """
        reply = self._command("stats reset" if reset else "stats")
        stats: dict[str, Any] = {"elapsed_cycles": reply["elapsed_cycles"], "frequency_hz": reply["frequency_hz"]}
        for role, plural in (("control_tick", "control_ticks"), ("telemetry_frame", "telemetry_frames")):
            region = reply["regions"].get(role)
            calls = region["calls"] if region else 0
            stats[plural] = calls
            stats[f"{role}_cycles_mean"] = region["total_cycles"] / calls if calls else None
            stats[f"{role}_cycles_max"] = region["max_cycles"] if calls else None
        elapsed = reply["elapsed_cycles"]
        stats["cpu_use_fraction"] = reply["busy_cycles"] / elapsed if elapsed else None
        stats["stack_bytes_max"] = reply["stack_bytes_max"]
        stats["regions"] = reply["regions"]
        stats["serial"] = reply["serial"]
        stats["simulator_steps"] = reply["simulator_steps"]
        return stats
