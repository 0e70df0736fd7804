"""The daemon's own simulated board (``phantom daemon --sim``), kept alive, behind a port path that never changes.

The simulated board comes from a factory the daemon is given (the command line passes the HIL package's
``SimulatedBoard``: the real firmware in simavr; the host does not import the HIL package). It lives in a
temporary folder that changes each time it starts; the daemon's serial transport opens a symlink of ours
instead, which is pointed at the current board. A watch polls the board's plant: its true gland volume feeds ``status``
(``plant_volume_ml``); if the simulator died, the daemon says so and starts a new one behind the same path
(the link session reconnects by itself, and the daemon restores its setpoints).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

from phantom import process_temporary_folder

logger = logging.getLogger(__name__)

#: How often (s) the watch polls the simulated plant.
WATCH_PERIOD_S = 0.5

#: What the keeper tells people: ``(kind, text, level)``.
EventSink = Callable[[str, str, str], None]


class SimulatedBoard(Protocol):
    """What the keeper needs of a simulated board (``phantom.hil.sim.SimulatedBoard`` is one)."""

    @property
    def port(self) -> str:
        """The serial port (a pseudo-terminal) of the running board."""

    def start(self) -> object:
        """Start the board (blocking)."""

    def stop(self) -> None:
        """Stop the board (blocking)."""

    def plant_state(self) -> dict[str, Any]:
        """The simulated plant's state; raises when the simulator is gone."""


#: Builds a simulated board running at a speed-up (1: real time).
SimulatedBoardFactory = Callable[[float], SimulatedBoard]


def plant_volume_ml(plant_state: dict[str, Any]) -> float | None:
    """The simulated plant's true gland volume (ml) from ``SimulatedBoard.plant_state()``, when it has one."""
    value = plant_state.get("gland_volume_ml")
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else None


class SimulatedBoardKeeper:
    """Start, watch and restart the daemon's simulated board.

    Parameters
    ----------
    speed : float
        The board's speed-up (1: real time).
    on_event : callable(kind, text, level)
        Where a death and a restart are reported.
    board_factory : callable(speed) -> SimulatedBoard
        Builds a board.
    """

    def __init__(self, speed: float, on_event: EventSink, board_factory: SimulatedBoardFactory):
        self.speed = speed
        self.on_event = on_event
        self._factory = board_factory
        self._folder = process_temporary_folder("phantomd-sim-")
        self.port = str(Path(self._folder.name) / "board")
        self.board: SimulatedBoard | None = None
        self.restarts = 0
        self.plant_volume_ml: float | None = None

    def start(self) -> None:
        """Start a board and point the port at it (blocking: run it in an executor)."""
        board = self._factory(self.speed)
        board.start()
        link = self.port + ".new"
        with contextlib.suppress(FileNotFoundError):
            os.unlink(link)
        os.symlink(board.port, link)
        os.replace(link, self.port)
        self.board = board

    def poll(self) -> bool:
        """Read the plant once (blocking); False when the simulator does not answer."""
        if self.board is None:
            return False
        try:
            state = self.board.plant_state()
        except Exception as error:  # any failure of the harness's pipe means the simulator is gone
            logger.debug("the simulated board did not answer: %s", error)
            return False
        self.plant_volume_ml = plant_volume_ml(state)
        return True

    def gaps_said(self) -> str | None:
        """What the simulated board heard of its host lately, in words (blocking): the last gap in the host's bytes
        over a quarter second of its time and how the simulator ran meanwhile; None when it does not answer."""
        if self.board is None:
            return None
        try:
            state = self.board.plant_state()
        except Exception:  # the simulator is gone: watch() says so
            return None
        running = f"the simulator running at {state.get('scheduling', 'an unknown priority')}"
        gaps = state.get("host_gaps") or []
        if not gaps:
            return f"the simulated board saw no gap over 0.25 s of its time in the host's bytes ({running})"
        _, board_s, gap_s, given_up_s, queued = gaps[-1]
        return (f"the simulated board's last gap in the host's bytes: {gap_s:.3f} s of its time, ending at "
                f"{board_s:.3f} s; meanwhile the simulator gave up {given_up_s:.3f} s of wall clock (its own stalls) "
                f"and {queued} byte(s) waited for its UART ({running})")

    async def watch(self) -> None:
        """Poll the plant; restart the simulator when it died (runs until cancelled)."""
        loop = asyncio.get_running_loop()
        while True:
            await asyncio.sleep(WATCH_PERIOD_S)
            if await loop.run_in_executor(None, self.poll):
                continue
            self.plant_volume_ml = None
            self.on_event("sim", "the simulated board (simavr) died: restarting it", "ERROR")
            await loop.run_in_executor(None, self._stop_board)
            try:
                await loop.run_in_executor(None, self.start)
            except Exception as error:
                self.on_event("sim", f"the simulated board could not be restarted: {error}; trying again", "ERROR")
                continue
            self.restarts += 1
            self.on_event("sim", f"simulated board restarted ({self.restarts} restart(s))", "WARN")

    def _stop_board(self) -> None:
        if self.board is not None:
            with contextlib.suppress(Exception):
                self.board.stop()
            self.board = None

    def close(self) -> None:
        """Stop the board and remove the port (blocking)."""
        self._stop_board()
        self._folder.cleanup()

    def status(self) -> dict[str, Any]:
        """For ``status``: the port and the restarts."""
        return {"port": self.port, "restarts": self.restarts}

