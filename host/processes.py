"""A process's children and descendants, read from /proc (Linux): what the daemon ends with a process it stops
(the model worker's pool, the response table's build and their solver processes)."""

from __future__ import annotations

import os
from pathlib import Path


def _children_by_parent() -> dict[int, list[int]]:
    """Every process's children (pids), by its parent's pid: each /proc/PID/stat's fourth field. Each process's stat
    says who its parent is whichever of the parent's threads started it, and needs no kernel option (a thread's
    /proc/PID/task/TID/children does: CONFIG_PROC_CHILDREN). A process that ends while they are read is left out."""
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            parent = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):  # ended meanwhile (ENOENT, ESRCH)
            continue
        children.setdefault(parent, []).append(int(entry.name))
    return children


def child_pids(pid: int | None = None) -> list[int]:
    """The children of a process (this one by default)."""
    return _children_by_parent().get(os.getpid() if pid is None else pid, [])


def descendants(pid: int) -> list[int]:
    """Every process below ``pid`` (its children, theirs...)."""
    children = _children_by_parent()
    found, pending = [], [pid]
    while pending:
        below = children.get(pending.pop(), [])
        found.extend(below)
        pending.extend(below)
    return found
