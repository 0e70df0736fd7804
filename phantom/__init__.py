"""Control stack for an active three-chamber prostate phantom.

The subpackages map to the repository's top-level folders: ``phantom.protocol`` (``protocol/``),
``phantom.model`` (``model/``), ``phantom.scan`` (``scan/``), ``phantom.host`` (``host/``) and
``phantom.hil`` (``hil/``); ``phantom.cli`` holds every command line. docs/architecture.md says which may
import which.
"""

from __future__ import annotations

import math
import numbers
import os
import shutil
import stat
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, TypeGuard

if TYPE_CHECKING:
    from phantom.host.client import AsyncPhantom, Phantom

__version__ = "0.1.0"

#: The repository root of an editable install; None in a wheel install, which has no firmware sources.
_checkout = Path(__file__).resolve().parent.parent
SOURCE_ROOT: Path | None = _checkout if (_checkout / "firmware").is_dir() else None


class PhantomError(Exception):
    """An error a user can act on: the message says what was wrong and what to do.

    The CLI prints these without a traceback and exits with status 2; anything else is a bug.
    """


class MissingExtraError(PhantomError):
    """A feature needs an optional dependency that is not installed; the message names the pip command."""


def install_command(extra: str) -> str:
    """The pip command that installs the optional dependencies ``extra`` (pyproject.toml's
    ``[project.optional-dependencies]``) into this installation: editable from a checkout, else by name."""
    if SOURCE_ROOT is not None:
        return f"pip install -e '{SOURCE_ROOT}[{extra}]'"
    return f"pip install 'active-prostate-phantom[{extra}]'"


@contextmanager
def require_extra(extra: str) -> Iterator[None]:
    """Imports inside this block come from the optional dependencies ``extra``: a missing one raises
    :class:`MissingExtraError` naming the package and the pip command that installs it.

    Examples
    --------
    >>> with require_extra("scan"):
    ...     import trimesh  # doctest: +SKIP
    """
    try:
        yield
    except ImportError as error:
        if error.name is None:  # installed, but it failed to load (a shared library, a broken install)
            raise MissingExtraError(f"an optional dependency failed to import ({error}); reinstall the optional "
                                    f"dependencies '{extra}': {install_command(extra)}") from error
        package = error.name.partition(".")[0]  # rerun, not rerun.chunk: the package a user would install
        raise MissingExtraError(f"{package} is not installed; it comes with the optional dependencies "
                                f"'{extra}': {install_command(extra)}") from error


def cache_dir(kind: str) -> Path:
    """The on-disk cache folder for one kind of artefact (``meshes``, ``compliance``, ``numba`` ...).

    ``$PHANTOM_CACHE_DIR`` overrides the root, else ``$XDG_CACHE_HOME/phantom`` or ``~/.cache/phantom``.
    """
    root = os.environ.get("PHANTOM_CACHE_DIR")
    if root is None:
        root = os.path.join(os.environ.get("XDG_CACHE_HOME", os.path.expanduser("~/.cache")), "phantom")
    path = Path(root) / kind
    path.mkdir(parents=True, exist_ok=True)
    return path


def connect(socket: str | Path | None = None, *, request_timeout_s: float = 60.0, ready_timeout_s: float = 300.0,
            on_wait: Callable[[str], None] | None = None) -> Phantom:
    """Connect to the running daemon (``phantom daemon``) and wait until it is ready: the Python API.

    >>> import phantom
    >>> with phantom.connect() as ph:                    # doctest: +SKIP
    ...     ph.set_volume(32.0)                          # returns once reached and settled
    ...     ph.surface().save_stl("phantom.stl")

    ``socket``: the daemon's socket (default: where the daemon listens by default); ``request_timeout_s``: how
    long one request may take; ``ready_timeout_s``: how long to wait for a daemon still starting (0: not at all);
    ``on_wait``: told what it is doing meanwhile. See :class:`phantom.host.client.Phantom` for the methods.
    """
    # the client is the host's: imported when a script connects, so that every part's import of the root stays
    # as light as it is
    from phantom.host.client import connect as connect_to_daemon

    return connect_to_daemon(socket, request_timeout_s=request_timeout_s, ready_timeout_s=ready_timeout_s,
                             on_wait=on_wait)


async def connect_async(socket: str | Path | None = None, *, request_timeout_s: float = 60.0,
                        ready_timeout_s: float = 300.0, on_wait: Callable[[str], None] | None = None) -> AsyncPhantom:
    """:func:`connect`'s asyncio twin: ``ph = await phantom.connect_async()``, then ``await ph.set_volume(32)``."""
    from phantom.host.client import connect_async as connect_to_daemon

    return await connect_to_daemon(socket, request_timeout_s=request_timeout_s, ready_timeout_s=ready_timeout_s,
                                   on_wait=on_wait)
#: The share of the memory available now that one command may plan to use for its arrays.
MEMORY_SHARE = 0.5


def memory_budget_bytes() -> int:
    """How much memory a command may plan to allocate: :data:`MEMORY_SHARE` of what the machine has available
    now (Linux's MemAvailable; the physical memory elsewhere). A command that would need more refuses before
    allocating, with its estimate, instead of swapping the machine to a halt."""
    try:
        with open("/proc/meminfo") as handle:
            for line in handle:
                if line.startswith("MemAvailable:"):
                    return int(MEMORY_SHARE * int(line.split()[1]) * 1024)
    except (OSError, ValueError, IndexError):
        pass
    return int(MEMORY_SHARE * os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))


def read_text(path: str | Path, max_bytes: int, what: str, error: type[PhantomError] = PhantomError) -> str:
    """The text of a file a user named (a scene, a config file, a measurement table): UTF-8, with or without a
    byte-order mark, at most ``max_bytes`` long. No more than that is read, so that a huge file (or /dev/zero)
    costs nothing before it is refused.

    Raises ``error`` (a PhantomError) with a one-line message that starts with ``what`` and the path: the file
    is missing, a folder, unreadable, too large, or not UTF-8 text.
    """
    path = Path(path)
    try:
        with open(path, "rb") as handle:
            data = handle.read(max_bytes + 1)
    except FileNotFoundError:
        raise error(f"{what} {path} does not exist: check the path") from None
    except IsADirectoryError:
        raise error(f"{what} {path} is a folder: give a file") from None
    except OSError as problem:
        raise error(f"{what} {path} cannot be read: {problem.strerror}") from None
    if len(data) > max_bytes:
        raise error(f"{what} {path} is larger than {max_bytes / 2**20:g} MiB: that is not one of ours (give the "
                    "right file)") from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as problem:
        utf16 = data.startswith((b"\xff\xfe", b"\xfe\xff"))
        raise error(f"{what} {path} is not UTF-8 text ({'it is UTF-16' if utf16 else f'byte {problem.start}'}): "
                    "save it as UTF-8") from None


def is_finite_number(value: object) -> TypeGuard[float]:
    """Whether ``value`` is a real number a float holds (numpy's too): not a bool or text, not inf or nan, nor an
    integer of hundreds of digits, which JSON and TOML read and ``math.isfinite`` or ``float()`` of it overflows."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def unique_keys(pairs: list[tuple[str, object]]) -> dict[str, object]:
    """``json.loads``'s ``object_pairs_hook`` that refuses a key given twice in an object (ValueError naming it):
    JSON itself keeps the last silently, so a file or a request that says two things would mean the second."""
    document: dict[str, object] = {}
    for key, value in pairs:
        if key in document:
            raise ValueError(f"duplicate key {key!r}")
        document[key] = value
    return document


@contextmanager
def written_atomically(path: str | Path, error: type[PhantomError] = PhantomError,
                       ends_with: bytes | None = None) -> Iterator[Path]:
    """A temporary file beside ``path`` for the caller to write, which becomes ``path`` only once it is whole.

    After the ``with`` body the file is checked (not empty; ending with ``ends_with`` when given: for writers
    that do not report a failed write, like gmsh's), flushed to the disk (fsync: a full disk is told here) and
    renamed over ``path``. On any failure the temporary file is removed, ``path`` is left as it was, and an
    OSError becomes ``error`` with a one-line message: a full disk never leaves a truncated file said to be
    written.
    """
    path = Path(path)
    try:
        descriptor, name = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    except OSError as problem:
        # the folder is missing, not a folder, or not the user's to write: not a full disk
        raise error(f"cannot write {path}: {problem.strerror or problem} in {path.parent}: give a folder you can "
                    "write") from None
    os.close(descriptor)
    temporary = Path(name)
    try:
        umask = os.umask(0o022)
        os.umask(umask)
        os.chmod(temporary, 0o666 & ~umask)  # the mode a plain open() gives, not mkstemp's 0600
        yield temporary
        with open(temporary, "rb+") as handle:
            size = handle.seek(0, os.SEEK_END)
            handle.seek(max(0, size - len(ends_with or b"")))
            if size == 0 or (ends_with is not None and handle.read() != ends_with):
                raise error(f"cannot write {path}: the file came out short ({size} bytes; the disk is full?): "
                            "free space or give another path")
            os.fsync(handle.fileno())
        os.replace(temporary, path)
    except OSError as problem:
        raise error(f"cannot write {path}: {problem.strerror or problem}: free space or give another path") from None
    finally:
        temporary.unlink(missing_ok=True)


def process_temporary_folder(prefix: str) -> tempfile.TemporaryDirectory[str]:
    """A temporary folder named after this process (``<prefix><pid>-XXXXXXXX`` in the temporary folder), removed
    when the returned object is cleaned up. A process killed with SIGKILL runs no cleanup: the folders of the same
    prefix that this user's processes left and that no longer run are removed here first."""
    root = Path(tempfile.gettempdir())
    for stale in root.glob(f"{prefix}*-*"):
        owner = stale.name[len(prefix):].split("-", 1)[0]
        if not owner.isdigit() or _process_runs(int(owner)):
            continue
        try:
            found = stale.lstat()
        except OSError:
            continue
        if stat.S_ISDIR(found.st_mode) and found.st_uid == os.getuid():
            shutil.rmtree(stale, ignore_errors=True)
    return tempfile.TemporaryDirectory(prefix=f"{prefix}{os.getpid()}-")


def _process_runs(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True
