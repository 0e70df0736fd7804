"""The solver's heap settings (model/fem/heap.py): inside a solve a large array freed and allocated again costs no
page faults, and the memory goes back to the system when the solve ends."""

import platform
import resource

import numpy as np
import pytest

from phantom.model.fem import heap

pytestmark = pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt and malloc_trim are glibc's")

SIZE = 64 << 20  # bytes: past glibc's largest dynamic mmap threshold (32 MB), as a 7 mm tangent's factor is


def _faults_of_reallocations(count: int) -> int:
    """Minor page faults while a 64 MB array is allocated, written and freed ``count`` times."""
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(count):
        block = np.empty(SIZE // 8)
        block[:] = 1.0
        del block
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before


def _resident_kb() -> int:
    with open("/proc/self/status") as status:
        return next(int(line.split()[1]) for line in status if line.startswith("VmRSS:"))


def test_a_freed_block_is_reused_without_page_faults_inside_a_solve() -> None:
    huge_pages = SIZE // (2 << 20)  # numpy asks for 2 MB pages for a large array: a fault each at the least
    outside = _faults_of_reallocations(4)
    assert outside >= 4 * huge_pages  # unmapped at each free, faulted in again at each write
    with heap.solving():
        _faults_of_reallocations(1)  # the heap grows once
        inside = _faults_of_reallocations(4)
    assert inside < huge_pages


def test_the_heap_is_given_back_when_the_solve_ends() -> None:
    with heap.solving():
        with heap.solving():  # nested: the outer one decides
            _faults_of_reallocations(1)
        held_kb = _resident_kb()
    assert _resident_kb() < held_kb - SIZE // 2048
