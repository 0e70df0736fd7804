"""Where the board link's process starts (:class:`phantom.host.link_process.LinkProcess`): it asks to die with the
daemon before it imports anything heavy (the link session, NumPy: seconds on a loaded machine), so that a daemon
killed while its link's process is still starting leaves nothing running (tests/test_daemon_parts.py)."""

from __future__ import annotations

import pickle
from multiprocessing.connection import Connection


def main(connection: Connection, parent_pid: int, settings: bytes) -> None:
    """The process's target: ``settings`` are :func:`phantom.host.link_child.serve_link`'s other arguments,
    pickled (unpickling them imports the session's modules)."""
    from phantom.model.cluster import exit_with_parent

    exit_with_parent(parent_pid)
    from phantom.host.link_child import serve_link

    serve_link(connection, *pickle.loads(settings))
