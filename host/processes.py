"""A process's children and descendants, read from /proc (Linux): what the daemon ends with a process it stops
(the model worker's pool, the response table's build and their solver processes)."""

from __future__ import annotations

import contextlib
from pathlib import Path


def child_pids(pid: int | None = None) -> list[int]:
    """The children of a process (this one by default): those of each of its threads, from /proc; none once it has
    ended. A thread that ends while they are read (the build's Dask threads come and go) has none: its folder is
    gone by the read (FileNotFoundError, or ESRCH), which in the table build's SIGTERM handler
    (phantom.host.startup) left the build to Python's slow exit."""
    pids: list[int] = []
    with contextlib.suppress(FileNotFoundError, ProcessLookupError):
        for task in Path(f"/proc/{'self' if pid is None else pid}/task").iterdir():
            with contextlib.suppress(FileNotFoundError, ProcessLookupError):
                pids.extend(int(child) for child in (task / "children").read_text().split())
    return pids


def descendants(pid: int) -> list[int]:
    """Every process below ``pid`` (its children, theirs...), from /proc (:func:`child_pids`)."""
    found, pending = [], [pid]
    while pending:
        children = child_pids(pending.pop())
        found.extend(children)
        pending.extend(children)
    return found
