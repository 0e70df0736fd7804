"""Who is behind the daemon's socket (issue 23, defect 7): a client checks, with the kernel's SO_PEERCRED, that the
process serving the socket runs as a user it trusts, so that a fake daemon another user left on a shared path
(``/tmp``) cannot answer ``vent`` with "vented"; and the fallback socket folder is private, not world-writable."""

from __future__ import annotations

import os
import pwd
import socket
import stat
import struct
from pathlib import Path

from phantom import PhantomError

#: The system user of the phantom service (host/systemd/phantomd.service ``User=``).
SERVICE_USER = "phantom"


def trusted_daemon_uids() -> set[int]:
    """The users a daemon may run as: this process's own, root, and the service user when it exists."""
    uids = {os.getuid(), 0}
    try:
        uids.add(pwd.getpwnam(SERVICE_USER).pw_uid)
    except KeyError:
        pass
    return uids


def peer_uid(connection: socket.socket) -> tuple[int, int]:
    """The (pid, uid) of the process at the other end of a connected Unix socket (SO_PEERCRED)."""
    pid, uid, _ = struct.unpack("3i", connection.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED,
                                                            struct.calcsize("3i")))
    return pid, uid


def check_daemon_peer(connection: socket.socket, path: str | Path) -> None:
    """Raise PhantomError unless the process serving ``path`` (``connection``, connected) runs as this user,
    root or the phantom service's user."""
    pid, uid = peer_uid(connection)
    if uid in trusted_daemon_uids():
        return
    try:
        name = pwd.getpwuid(uid).pw_name
    except KeyError:
        name = f"uid {uid}"
    raise PhantomError(f"{path} is served by user {name} (pid {pid}), not by you, root or the {SERVICE_USER} "
                       "service: it may be a fake daemon; do not trust it: pass the right --socket (or remove that "
                       "socket)")


def private_folder(path: Path) -> Path:
    """``path``, a folder only this user may write: created with mode 0700 if missing; PhantomError if it exists
    but is not a folder of this user's that no one else may write (another user made it first, to squat)."""
    try:
        path.mkdir(mode=0o700)
    except FileExistsError:
        pass
    except OSError as error:
        raise PhantomError(f"cannot make the socket folder {path}: {error.strerror}; pass --socket") from None
    found = os.lstat(path)
    if not stat.S_ISDIR(found.st_mode) or found.st_uid != os.getuid() or found.st_mode & 0o022:
        raise PhantomError(f"{path} is not a private folder of yours (owner uid {found.st_uid}, mode "
                           f"{stat.filemode(found.st_mode)}): someone else may have made it; remove it or pass "
                           "--socket")
    return path
