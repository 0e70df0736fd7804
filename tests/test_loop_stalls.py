"""The event loops' stall record (host/stalls.py): each notable stall with what it was made of, so that a stall in
a CI log says whether the loop's thread computed, waited for a core, lost its core to the hypervisor, or was
blocked, and in what."""

from __future__ import annotations

import asyncio
import os
import platform
import threading
import time

import pytest

from phantom.host.stalls import NOTABLE_STALL_MS, LoopStalls, blocked_in, stolen_ms


def _stall_once(block) -> list:
    """A probe on a loop of its own, the loop held up once by ``block()``; the notable stalls its status lists."""
    stalls = LoopStalls(period_s=0.01)

    async def run() -> None:
        probe = asyncio.ensure_future(stalls.probe())
        await asyncio.sleep(0.05)
        block()
        await asyncio.sleep(0.05)
        probe.cancel()

    asyncio.run(run())
    return stalls.to_json()["notable_stalls"]


def test_the_hypervisors_steal_is_read_and_never_goes_back():
    first = stolen_ms()
    assert first is not None and first >= 0.0  # Linux says, a VM or not
    assert stolen_ms() >= first


def test_a_blocked_loop_and_a_busy_one_are_told_apart():
    """Blocked (a sleep: as a read that waits) the thread ran little of the stall; busy, it ran nearly all of it.
    Each stall lists seconds ago, ms late, ms waiting for a core, ms of garbage collection, ms on a core, major
    page faults, ms the hypervisor stole meanwhile (a tick, 10 ms, at a time; 0 on bare metal), and what the loop's
    thread was seen in."""
    (blocked,) = [stall for stall in _stall_once(lambda: time.sleep(0.3)) if stall[1] > 100]
    ago_s, late_ms, queued_ms, gc_ms, ran_ms, faults, stolen, seen = blocked
    assert 0 <= ago_s < 1 and 250 < late_ms < 1000 and queued_ms >= 0 and gc_ms >= 0 and faults >= 0
    assert ran_ms < 50 and stolen is not None and stolen >= 0
    if platform.machine() == "x86_64":
        assert seen.startswith("clock_nanosleep (hrtimer_nanosleep) x"), seen

    def spin() -> None:
        until = time.monotonic() + 0.15
        while time.monotonic() < until:
            pass

    (busy,) = [stall for stall in _stall_once(spin) if stall[1] > 100]
    # on a core, or waiting for one (a loaded machine), or taken by the hypervisor: not blocked; and no look at
    # it, as it held the interpreter's lock
    assert busy[4] + busy[2] + busy[6] > 0.6 * busy[1], busy


def test_a_loop_blocked_in_a_write_is_seen_in_it_with_its_file():
    """The board link's loop stalled 0.4-0.8 s in CI with little time on a core, none waiting for one and no
    steal: blocked in something the stall record did not say. Here a write into a full pipe, which another
    thread drains 0.4 s later."""
    reading, writing = os.pipe()
    full = b"x" * 65536
    os.set_blocking(writing, False)
    while True:
        try:
            os.write(writing, full)
        except BlockingIOError:
            break
    os.set_blocking(writing, True)

    def drain_later() -> None:
        time.sleep(0.4)
        while os.read(reading, 65536):
            pass

    drain = threading.Thread(target=drain_later, daemon=True)
    drain.start()
    stalls = _stall_once(lambda: os.write(writing, b"y" * 4096))
    pipe = os.fstat(reading).st_ino
    os.close(writing)
    drain.join(5)
    os.close(reading)
    (blocked,) = [stall for stall in stalls if stall[1] > 300]
    if platform.machine() != "x86_64":
        pytest.skip("the system call's name is x86-64's")
    assert blocked[7].startswith(f"write pipe:[{pipe}] ("), blocked


def test_only_stalls_over_the_notable_line_are_listed():
    stalls = LoopStalls()
    stalls.record(1.0, NOTABLE_STALL_MS / 2, 0.0, 0.0, 1.0, 0, 0.0)
    stalls.record(2.0, NOTABLE_STALL_MS * 3, 1.0, 0.0, 2.0, 0, 20.0, "read pipe:[7] (anon_pipe_read) x2")
    (listed,) = stalls.to_json()["notable_stalls"]
    assert listed[1:] == [NOTABLE_STALL_MS * 3, 1.0, 0.0, 2.0, 0, 20.0, "read pipe:[7] (anon_pipe_read) x2"]
    assert stalls.to_json()["longest_stall_ms"] == NOTABLE_STALL_MS * 3


def test_what_a_thread_is_doing_in_the_kernels_words():
    reading, writing = os.pipe()
    tids = []
    reader = threading.Thread(target=lambda: (tids.append(threading.get_native_id()), os.read(reading, 1)))
    reader.start()
    time.sleep(0.2)
    seen, pipe = blocked_in(tids[0]), os.fstat(reading).st_ino
    os.write(writing, b"x")
    reader.join()
    os.close(reading)
    os.close(writing)
    if platform.machine() == "x86_64":  # where the kernel has it sleep: anon_pipe_read here, pipe_read before 6.x
        assert seen.startswith(f"read pipe:[{pipe}] (") and seen.endswith("pipe_read)"), seen
    assert blocked_in(2**22 + 12345) is None  # no such thread


def test_the_stalls_before_a_fault_are_said_in_words_the_longest_with_its_parts():
    """What the daemon says when DEAD_HOST latches: the link loop's stalls of the last seconds, the longest with
    what it was made of; a loop that ran on time says so; older stalls are left out."""
    from phantom.host.stalls import said_stalls

    blocked = _stall_once(lambda: time.sleep(0.3))
    said = said_stalls(blocked, 5.0)
    longest = max(stall[1] for stall in blocked)
    assert said.startswith(f"{len(blocked)} stall(s) over {NOTABLE_STALL_MS:g} ms in the last 5 s, the longest "
                           f"{longest:g} ms"), said
    assert 290 <= longest < 1000 and "ran " in said, said
    assert said_stalls(blocked, 0.0) == f"no stall over {NOTABLE_STALL_MS:g} ms in the last 0 s: it ran on time"
    assert said_stalls([], 3.0).endswith("it ran on time")
    # every part the record kept is said (a part the machine does not give, None, is not)
    stall = [0.5, 612.0, 1.5, None, 3.0, 2, 0.0, "write (/dev/pts/3)"]
    assert said_stalls([stall], 3.0) == ("1 stall(s) over 10 ms in the last 3 s, the longest 612 ms 0.5 s ago (ran 3 "
                                         "ms, waited for a core 1.5 ms, stolen by the hypervisor 0 ms, 2 page faults, "
                                         "blocked in write (/dev/pts/3))")
