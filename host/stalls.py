"""How late an event loop runs its timers: :class:`LoopStalls`, the daemon's measure of its own loop's stalls
(status ``event_loop``) and of the board link's loop (status ``link_detail.event_loop``); and what each notable
stall was made of: the time its thread waited for a core (the kernel's run-queue delay) and the cyclic garbage
collector's pauses (:class:`GcPauses`: every thread of the process waits for a collection), the time the
hypervisor took the machine's virtual cores meanwhile (:func:`stolen_ms`), and what the loop's thread was
blocked in (:class:`BlockSampler`: the kernel's account of it, looked at from a thread beside it)."""

from __future__ import annotations

import asyncio
import gc
import os
import platform
import resource
import threading
import time
from collections import Counter, deque
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
#: The block sampler looks this often (s) whether the loop has run its probe lately, and at the loop's thread
#: when it has not for :data:`BLOCK_LOOK_AFTER_S`.
BLOCK_LOOK_S = 0.05
BLOCK_LOOK_AFTER_S = 0.1
#: x86-64's numbers of the system calls a loop's thread may be found in (elsewhere the number is said).
SYSCALL_NAMES = {0: "read", 1: "write", 3: "close", 7: "poll", 16: "ioctl", 17: "pread64", 18: "pwrite64",
                 20: "writev", 23: "select", 35: "nanosleep", 74: "fsync", 75: "fdatasync", 202: "futex",
                 230: "clock_nanosleep", 232: "epoll_wait", 257: "openat", 270: "pselect6", 271: "ppoll",
                 281: "epoll_pwait", 441: "epoll_pwait2"}


def thread_times_ms() -> tuple[float, float, int] | None:
    """The calling thread's time on a core and waiting for one (ms) since it started, from
    ``/proc/thread-self/schedstat``, and its major page faults (``getrusage``); None where the kernel has none."""
    try:
        with open("/proc/thread-self/schedstat", "rb") as schedstat:
            ran_ns, waited_ns = schedstat.read().split()[:2]
        return int(ran_ns) / 1e6, int(waited_ns) / 1e6, resource.getrusage(resource.RUSAGE_THREAD).ru_majflt
    except (OSError, IndexError, ValueError, AttributeError):
        return None


def stolen_ms() -> float | None:
    """The time the hypervisor ran something else while this machine's virtual cores had work to do (ms, all
    cores together, since boot): ``/proc/stat``'s steal. A thread whose core was taken so looks, from inside,
    like a thread blocked: little time on a core and none waiting for one (a loop stall of 788 ms of the board
    link's, 7.8 ms of it on a core, in a CI run on a VM that lost 2.1 s to steal in 7 minutes). None where the
    kernel does not say; 0 on bare metal. A read costs about 15 us."""
    try:
        with open("/proc/stat", "rb") as stat:
            fields = stat.readline().split()
        return int(fields[8]) * 1e3 / os.sysconf("SC_CLK_TCK")
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

    def install(self) -> None:
        if self._callback not in gc.callbacks:
            gc.callbacks.append(self._callback)

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


def blocked_in(tid: int) -> str | None:
    """What the thread ``tid`` of this process is doing now, in the kernel's words: ``running``, or the system
    call it is in (its name on x86-64, its file for a read or write: ``write /dev/pts/3``) and where it sleeps
    (``/proc``'s wchan: ``n_tty_write``, ``anon_pipe_read``, ``balance_dirty_pages``...). None where the kernel
    does not say."""
    try:
        with open(f"/proc/self/task/{tid}/syscall") as syscall:
            fields = syscall.read().split()
        with open(f"/proc/self/task/{tid}/wchan") as wchan:
            sleeping_in = wchan.read().strip()
    except OSError:
        return None
    if not fields or fields[0] == "running":
        return "running"
    number = int(fields[0])
    if number < 0:  # asleep outside a system call: a page fault's wait
        return f"a fault ({sleeping_in or '?'})"
    named = SYSCALL_NAMES.get(number, f"system call {number}") if platform.machine() == "x86_64" else \
        f"system call {number}"
    if named in ("read", "write", "pread64", "pwrite64", "writev", "fsync", "fdatasync", "ioctl") and len(fields) > 1:
        try:
            named += " " + os.readlink(f"/proc/self/fd/{int(fields[1], 16)}")
        except (OSError, ValueError):
            pass
    return f"{named} ({sleeping_in})" if sleeping_in and sleeping_in != "0" else named


class BlockSampler:
    """A thread that looks, while the loop's probe is late, at what the loop's thread is blocked in
    (:func:`blocked_in`), every :data:`BLOCK_LOOK_S` once the probe is :data:`BLOCK_LOOK_AFTER_S` late. A thread
    asleep in the kernel (a write that waits, a lock) has released the interpreter's lock, so this one can look;
    a loop that holds it (a long C call) leaves no look, and says so by that. Its looks: (monotonic s, what)."""

    def __init__(self, tid: int):
        self.tid = tid
        self.alive_s = time.monotonic()
        self.looks: deque[tuple[float, str]] = deque(maxlen=512)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="loop block sampler", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(BLOCK_LOOK_S):
            now_s = time.monotonic()
            if now_s - self.alive_s > BLOCK_LOOK_AFTER_S:
                seen = blocked_in(self.tid)
                if seen is not None:
                    self.looks.append((now_s, seen))

    def within(self, from_s: float, to_s: float) -> str | None:
        """What the looks between ``from_s`` and ``to_s`` saw, the commonest first with its count: ``write
        /dev/pts/3 (n_tty_write) x6, running x1``; None without a look."""
        seen = Counter(what for at_s, what in list(self.looks) if from_s <= at_s <= to_s)
        return ", ".join(f"{what} x{count}" for what, count in seen.most_common(3)) or None

    def stop(self) -> None:
        self._stop.set()


def said_stalls(notable_stalls: list[list[Any]], within_s: float) -> str:
    """A loop's ``notable_stalls`` (its status's: how long ago (s), how late (ms), then what it was made of) of the
    last ``within_s`` seconds in words: how many, and the longest with its parts."""
    recent = [stall for stall in notable_stalls if stall[0] <= within_s]
    if not recent:
        return f"no stall over {NOTABLE_STALL_MS:g} ms in the last {within_s:g} s: it ran on time"
    ago_s, late_ms, queued_ms, gc_ms, ran_ms, page_faults, stolen, blocked_in = max(recent, key=lambda s: s[1])
    parts = [f"{label} {value:g} ms" for label, value in (("ran", ran_ms), ("waited for a core", queued_ms),
                                                          ("in the garbage collector", gc_ms),
                                                          ("stolen by the hypervisor", stolen)) if value is not None]
    if page_faults:
        parts.append(f"{page_faults:g} page faults")
    if blocked_in:
        parts.append(f"blocked in {blocked_in}")
    return (f"{len(recent)} stall(s) over {NOTABLE_STALL_MS:g} ms in the last {within_s:g} s, the longest "
            f"{late_ms:g} ms {ago_s:.1f} s ago" + (f" ({', '.join(parts)})" if parts else ""))


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
        #: waited for a core, ms of it the garbage collector ran, ms the thread ran, its major page faults, ms the
        #: hypervisor took from the machine's cores meanwhile (all together: a tick is 10 ms), what the thread was
        #: seen blocked in (:meth:`BlockSampler.within`; stalls under BLOCK_LOOK_AFTER_S have no look); None
        #: where the kernel does not say)
        self.notable: deque[tuple[float, float, float | None, float, float | None, float | None, float | None,
                                  str | None]] = deque(maxlen=256)
        self.sampler: BlockSampler | None = None

    async def probe(self) -> None:
        """Runs until cancelled, with a :class:`BlockSampler` of the loop's thread beside it."""
        times, stolen = thread_times_ms(), stolen_ms()
        self.sampler = sampler = BlockSampler(threading.get_native_id())
        try:
            while True:
                due_s = time.monotonic() + self.period_s
                await asyncio.sleep(self.period_s)
                now_s = sampler.alive_s = time.monotonic()
                late_ms = max(0.0, now_s - due_s) * 1e3
                before, times = times, thread_times_ms()
                stolen_before, stolen = stolen, stolen_ms()
                parts: tuple[float | None, ...] = (None, None, None)
                if before is not None and times is not None:
                    parts = tuple(after - earlier for after, earlier in zip(times, before, strict=True))
                notable = late_ms > NOTABLE_STALL_MS
                self.record(now_s, late_ms, parts[1],
                            GC_PAUSES.within_ms(due_s - self.period_s, now_s) if notable else 0.0,
                            parts[0], parts[2],
                            None if stolen is None or stolen_before is None else stolen - stolen_before,
                            sampler.within(due_s - self.period_s, now_s) if notable else None)
        finally:
            sampler.stop()

    def record(self, now_s: float, late_ms: float, queued_ms: float | None = None, gc_ms: float = 0.0,
               ran_ms: float | None = None, page_faults: float | None = None, stolen_ms: float | None = None,
               blocked_in: str | None = None) -> None:
        self.probes += 1
        self.longest_ms = max(self.longest_ms, late_ms)
        if late_ms > NOTABLE_STALL_MS:
            self.notable.append((now_s, late_ms, queued_ms, gc_ms, ran_ms, page_faults, stolen_ms, blocked_in))
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
                "notable_stalls": [[round(now_s - at_s, 3), round(late, 1), *(None if part is None else round(part, 1)
                                                                   for part in parts), blocked]
                                   for at_s, late, *parts, blocked in list(self.notable)[-NOTABLE_SHOWN:]]}
