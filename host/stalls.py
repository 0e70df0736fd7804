"""How late an event loop runs its timers: :class:`LoopStalls`, the daemon's measure of its own loop's stalls
(status ``event_loop``) and of the board link's loop (status ``link_detail.event_loop``)."""

from __future__ import annotations

import asyncio
import time
from collections import deque
from typing import Any

#: The probe's period (s): a timer this often, whose lateness is the loop's stall (a stall of d makes it between
#: d - period and d late).
PROBE_S = 0.02
#: The status's recent stall covers this long (s).
RECENT_S = 60.0
#: Stalls longer than this (ms) are listed in the status (``notable_stalls``: how long ago, how long).
NOTABLE_STALL_MS = 10.0
#: The status lists this many of them, the latest.
NOTABLE_SHOWN = 32


class LoopStalls:
    """How late the event loop runs a timer: a probe every ``period_s``; the longest lateness since the start and
    over the last ``recent_s`` (ms). Whatever stalls the loop (work done inside it) delays every timer by as much:
    the control loop's, an acknowledged command's retransmission, a client's answer."""

    def __init__(self, period_s: float = PROBE_S, recent_s: float = RECENT_S):
        self.period_s = period_s
        self.recent_s = recent_s
        self.longest_ms = 0.0
        self.probes = 0
        self._recent: deque[tuple[float, float]] = deque()
        #: the latest probes later than :data:`NOTABLE_STALL_MS`: (monotonic s, ms)
        self.notable: deque[tuple[float, float]] = deque(maxlen=256)

    async def probe(self) -> None:
        """Runs until cancelled."""
        while True:
            due_s = time.monotonic() + self.period_s
            await asyncio.sleep(self.period_s)
            now_s = time.monotonic()
            self.record(now_s, max(0.0, now_s - due_s) * 1e3)

    def record(self, now_s: float, late_ms: float) -> None:
        self.probes += 1
        self.longest_ms = max(self.longest_ms, late_ms)
        if late_ms > NOTABLE_STALL_MS:
            self.notable.append((now_s, late_ms))
        # the window's maximum: later probes that are at least as late make earlier ones irrelevant
        while self._recent and self._recent[-1][1] <= late_ms:
            self._recent.pop()
        self._recent.append((now_s, late_ms))

    def to_json(self) -> dict[str, Any]:
        now_s = time.monotonic()
        while self._recent and self._recent[0][0] < now_s - self.recent_s:
            self._recent.popleft()
        recent = self._recent[0][1] if self._recent else 0.0
        return {"longest_stall_ms": round(self.longest_ms, 1), "recent_stall_ms": round(recent, 1),
                "recent_s": self.recent_s, "probe_period_ms": self.period_s * 1e3,
                "notable_stalls": [[round(now_s - at_s, 3), round(late, 1)] for at_s, late in
                                   list(self.notable)[-NOTABLE_SHOWN:]]}
