"""Control stack for an active three-chamber prostate phantom.

The subpackages map to the repository's top-level folders: ``phantom.model`` (``model/``),
``phantom.protocol`` (``protocol/``), ``phantom.host`` (``host/``) and ``phantom.hil`` (``hil/``).
"""

import os
from pathlib import Path

__version__ = "0.1.0"

#: The repository root of an editable install; None in a wheel install, which has no firmware sources.
_checkout = Path(__file__).resolve().parent.parent
SOURCE_ROOT: Path | None = _checkout if (_checkout / "firmware").is_dir() else None


class PhantomError(Exception):
    """An error a user can act on: the message says what was wrong and what to do.

    The CLI prints these without a traceback and exits with status 2; anything else is a bug.
    """


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
