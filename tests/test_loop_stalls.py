"""The event loops' stall record (host/stalls.py): each notable stall with what it was made of, so that a stall in
a CI log says whether the loop's thread computed, waited for a core, was blocked, or lost its core to the
hypervisor."""

from __future__ import annotations

import asyncio
import time

from phantom.host.stalls import NOTABLE_STALL_MS, LoopStalls, stolen_ms


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
    page faults and ms the hypervisor stole meanwhile (a tick, 10 ms, at a time; 0 on bare metal)."""
    (blocked,) = [stall for stall in _stall_once(lambda: time.sleep(0.15)) if stall[1] > 100]
    ago_s, late_ms, queued_ms, gc_ms, ran_ms, faults, stolen = blocked
    assert 0 <= ago_s < 1 and 100 < late_ms < 1000 and queued_ms >= 0 and gc_ms >= 0 and faults >= 0
    assert ran_ms < 50 and stolen is not None and stolen >= 0

    def spin() -> None:
        until = time.monotonic() + 0.15
        while time.monotonic() < until:
            pass

    (busy,) = [stall for stall in _stall_once(spin) if stall[1] > 100]
    # on a core, or waiting for one (a loaded machine), or taken by the hypervisor: not blocked
    assert busy[4] + busy[2] + busy[6] > 0.6 * busy[1], busy


def test_only_stalls_over_the_notable_line_are_listed():
    stalls = LoopStalls()
    stalls.record(1.0, NOTABLE_STALL_MS / 2, 0.0, 0.0, 1.0, 0, 0.0)
    stalls.record(2.0, NOTABLE_STALL_MS * 3, 1.0, 0.0, 2.0, 0, 20.0)
    (listed,) = stalls.to_json()["notable_stalls"]
    assert listed[1:] == [NOTABLE_STALL_MS * 3, 1.0, 0.0, 2.0, 0, 20.0]
    assert stalls.to_json()["longest_stall_ms"] == NOTABLE_STALL_MS * 3
