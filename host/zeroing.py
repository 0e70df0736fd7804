"""Zeroing the board's pressure sensors (ZERO_SENSORS): asked on request, or after connecting to a vented phantom,
waiting for still readings the way the board itself judges them (:class:`phantom.host.board_watch.Stillness`).

Targets wait while a zero is in progress (their setpoints would cancel it): :class:`SensorZero` tells the control
core (``on_zeroing``) when it starts, how far it is, and when it is over.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable
from typing import Any

from phantom.host.api import ApiError
from phantom.host.board_watch import Stillness
from phantom.host.session import CommandRejected, LinkDown, Telemetry

#: After connecting, how long the daemon keeps asking a board that answers NOT_SETTLED (s): the board zeroes only
#: once every reading has been still for 2 s, which a phantom still deflating after a vent or a reset takes a
#: while to be; the daemon asks again each time the readings have been still that long (its status says how far
#: they are), and says the zero is missing if they never are.
ZERO_SETTLE_LIMIT_S = 60.0
#: How often the wait looks at the readings (s); the board is asked again at least every four of these.
ZERO_RETRY_S = 0.5
#: Why targets wait while a zero is in progress (one reason for the whole zero: the targets that wait say it once;
#: its progress is the status's ``zero``).
ZEROING_WHY = "ZERO_SENSORS once the readings are still (phantom status shows how far)"
#: Why the board refuses ZERO_SENSORS, by NACK status (protocol/spec.toml); other statuses are named as such.
ZERO_REFUSALS: dict[str, str] = {
    "NOT_VENTED": "a setpoint or a blower is on: vent first (phantom vent) and wait for the chambers to empty",
    "NOT_SETTLED": "the readings are not steady yet: wait a few seconds after venting and try again",
    "ZERO_OUT_OF_RANGE": "a measured zero is too far from the sensor's nominal zero (a chamber still "
                         "pressurised, or a sensor fault); the old zero is kept",
}


class SensorZero:
    """ZERO_SENSORS with its waits; ``state`` is what the status's ``zero`` shows."""

    def __init__(self, command: Callable[[str], Awaitable[Any]], telemetry: Callable[[], Telemetry | None],
                 stillness: Callable[[], Stillness], on_zeroing: Callable[[str | None], None],
                 event: Callable[[str, str, str], None]):
        self._command = command
        self._telemetry = telemetry
        self._stillness = stillness
        self._on_zeroing = on_zeroing
        self._event = event
        self.state: dict[str, Any] = {"state": "not asked", "text": "no zero asked since the daemon started"}
        self._done = asyncio.Event()
        self._done.set()

    async def after_connecting(self) -> None:
        """ZERO_SENSORS after connecting to a vented phantom, waiting for still readings; a refusal is an event
        and ``state`` says the zero is missing."""
        try:
            acknowledged = await self.sensors(settle_limit_s=ZERO_SETTLE_LIMIT_S)
            self._event("zero", "sensors zeroed after connecting (the phantom was vented)"
                        + ("" if acknowledged else "; the board's ACK was not seen (a retransmission found it busy)"),
                        "INFO")
        except ApiError as error:
            self.state = {"state": "missing", "text": f"the sensors were not zeroed after connecting: {error}"}
            self._event("zero", f"sensors not zeroed after connecting: {error}", "WARN")

    async def sensors(self, settle_limit_s: float = 0.0) -> bool:
        """ZERO_SENSORS; True when acknowledged, False when the board was found zeroing already (its ACK comes
        after the zeroing, about 128 ms, so a retransmission can meet BUSY while our own request runs: then the
        telemetry is followed until it leaves ZEROING). A board that answers NOT_SETTLED is asked again, for up
        to ``settle_limit_s`` seconds, each time the readings have been still for as long as the board needs.
        Raises ApiError ``rejected`` saying why the board refused, ``link_down`` without a board."""
        self._done.clear()
        self._on_zeroing(ZEROING_WHY)
        give_up_s = time.monotonic() + settle_limit_s
        try:
            while True:
                try:
                    await self._command("ZERO_SENSORS")
                    self.state = {"state": "zeroed", "text": f"zeroed at {time.strftime('%H:%M:%S')}"}
                    return True
                except LinkDown as error:
                    raise ApiError("link_down", str(error)) from error
                except CommandRejected as error:
                    if error.status == "BUSY":
                        return await self._wait_zeroing_over()
                    if error.status != "NOT_SETTLED" or time.monotonic() + ZERO_RETRY_S > give_up_s:
                        why = ZERO_REFUSALS.get(error.status, f"the board answered {error.status}")
                        raise ApiError("rejected", f"the board refused to zero its sensors: {error.status} "
                                       f"({why})") from error
                await self._wait_still(give_up_s)
        finally:
            self._on_zeroing(None)
            self._done.set()

    async def _wait_still(self, give_up_s: float) -> None:
        """Until the readings have been still for the board's settle time (or the next try is due anyway: the
        board is the judge), with the progress in ``state``."""
        asked_s = time.monotonic()
        while time.monotonic() < give_up_s:
            still = self._stillness()
            self.state = {"state": "waiting", "text": "waiting for the chambers to be still before zeroing "
                          f"(still for {still.still_for_s:.1f} of {still.needed_s:g} s; moved {still.moved_pa:.0f} Pa)",
                          "still_for_s": still.still_for_s, "needed_s": still.needed_s}
            if still.still or time.monotonic() - asked_s >= ZERO_RETRY_S * 4:
                return
            await asyncio.sleep(ZERO_RETRY_S)

    async def _wait_zeroing_over(self) -> bool:
        for _ in range(40):
            await asyncio.sleep(0.05)
            telemetry = self._telemetry()
            if telemetry is not None and "ZEROING" not in telemetry.states:
                self.state = {"state": "zeroed", "text": f"zeroed at {time.strftime('%H:%M:%S')}"}
                return False
        raise ApiError("rejected", "the board stayed busy zeroing its sensors for 2 s: try again")

    async def over(self) -> None:
        """Wait until a zero in progress is over (a target would cancel it)."""
        await asyncio.wait_for(self._done.wait(), ZERO_SETTLE_LIMIT_S + 5.0)
