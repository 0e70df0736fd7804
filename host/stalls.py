"""How late an event loop runs its timers: :class:`LoopStalls`, the daemon's measure of its own loop's stalls
(status ``event_loop``) and of the board link's loop (status ``link_detail.event_loop``); and what each notable
stall was made of: the time its thread waited for a core (the kernel's run-queue delay) and the cyclic garbage
collector's pauses (:class:`GcPauses`: every thread of the process waits for a collection)."""

from __future__ import annotations

import asyncio
import gc
import threading
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


def run_queue_wait_ms() -> float | None:
    """How long (ms) the calling thread has waited for a core since it started: the second figure of
    ``/proc/thread-self/schedstat`` (None where the kernel has none)."""
    try:
        with open("/proc/thread-self/schedstat", "rb") as schedstat:
            return int(schedstat.read().split()[1]) / 1e6
    except (OSError, IndexError, ValueError):
        return None


class GcPauses:
    """The cyclic garbage collector's pauses in this process, timed by ``gc.callbacks``: a collection holds the
    GIL, so every thread (the board link's too) waits for it. Keeps the latest (start s, end s, generation) on
    the monotonic clock, the count and longest pause per generation."""

    def __init__(self) -> None:
        self.recent: deque[tuple[float, float, int]] = deque(maxlen=1024)
        self.collections = [0, 0, 0]
        self.longest_ms = [0.0, 0.0, 0.0]
        self._started_s: float | None = None
        self._lock = threading.Lock()

    def install(self) -> GcPauses:
        if self._callback not in gc.callbacks:
            gc.callbacks.append(self._callback)
        return self

    def uninstall(self) -> None:
        if self._callback in gc.callbacks:
            gc.callbacks.remove(self._callback)

    def _callback(self, phase: str, info: dict[str, int]) -> None:
        now_s = time.monotonic()
        if phase == "start":
            self._started_s = now_s
            return
        started_s, self._started_s = self._started_s, None
        if started_s is None:
            return
        generation = info.get("generation", 2)
        with self._lock:
            self.recent.append((started_s, now_s, generation))
            self.collections[generation] += 1
            self.longest_ms[generation] = max(self.longest_ms[generation], (now_s - started_s) * 1e3)

    def within_ms(self, from_s: float, to_s: float) -> float:
        """How long (ms) collections ran between ``from_s`` and ``to_s`` (monotonic s)."""
        with self._lock:
            pauses = list(self.recent)
        return sum(max(0.0, min(end_s, to_s) - max(start_s, from_s)) for start_s, end_s, _ in pauses) * 1e3

    def to_json(self) -> dict[str, Any]:
        return {"collections": list(self.collections), "longest_ms": [round(ms, 1) for ms in self.longest_ms],
                "frozen": gc.get_freeze_count()}


#: This process's collector pauses (installed by the daemon at start-up).
GC_PAUSES = GcPauses()


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
        #: the latest probes later than :data:`NOTABLE_STALL_MS`: (monotonic s, ms, ms of it the loop's thread
        #: waited for a core or None, ms of it the garbage collector ran)
        self.notable: deque[tuple[float, float, float | None, float]] = deque(maxlen=256)

    async def probe(self) -> None:
        """Runs until cancelled."""
        waited_ms = run_queue_wait_ms()
        while True:
            due_s = time.monotonic() + self.period_s
            await asyncio.sleep(self.period_s)
            now_s = time.monotonic()
            late_ms = max(0.0, now_s - due_s) * 1e3
            waited_before_ms, waited_ms = waited_ms, run_queue_wait_ms()
            queued_ms = None if waited_ms is None or waited_before_ms is None else waited_ms - waited_before_ms
            self.record(now_s, late_ms, queued_ms,
                        GC_PAUSES.within_ms(due_s - self.period_s, now_s) if late_ms > NOTABLE_STALL_MS else 0.0)

    def record(self, now_s: float, late_ms: float, queued_ms: float | None = None, gc_ms: float = 0.0) -> None:
        self.probes += 1
        self.longest_ms = max(self.longest_ms, late_ms)
        if late_ms > NOTABLE_STALL_MS:
            self.notable.append((now_s, late_ms, queued_ms, gc_ms))
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
                "recent_s": self.recent_s, "probe_period_ms": self.period_s * 1e3, "gc": GC_PAUSES.to_json(),
                "notable_stalls": [[round(now_s - at_s, 3), round(late, 1),
                                    None if queued is None else round(queued, 1), round(gc_ms, 1)]
                                   for at_s, late, queued, gc_ms in list(self.notable)[-NOTABLE_SHOWN:]]}
