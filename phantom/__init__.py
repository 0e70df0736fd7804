"""Control stack for an active three-chamber prostate phantom.

The subpackages map to the repository's top-level folders: ``phantom.protocol`` (``protocol/``),
``phantom.model`` (``model/``), ``phantom.scan`` (``scan/``), ``phantom.host`` (``host/``) and
``phantom.hil`` (``hil/``); ``phantom.cli`` holds every command line. docs/architecture.md says which may
import which.
"""

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

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
