"""How the FEM's numba code is compiled: the ahead-of-time build when it matches the sources, else numba's JIT.

The element kernels (:mod:`phantom.model.fem.kernels`) and the material laws they call
(:mod:`phantom.model.fem.materials`) are decorated with :func:`kernel`. ``python -m phantom.model.fem.kernels``
(run by scripts/bootstrap.sh after an install) compiles the exported kernels ahead of time with numba.pycc into
``phantom.cache_dir("kernels")``, keyed by both files' sources (:data:`SOURCES`); while that build matches,
:data:`COMPILED` is it, :func:`kernel` leaves the Python source as it is and numba is never imported, which
saves a process 0.6 s (numba's import and its first-call start). Otherwise (no build, or
``PHANTOM_JIT_KERNELS=1``) :func:`kernel` is numba's JIT, cached on disk.
"""

import hashlib
import importlib.util
import os
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any, TypeVar, cast

import numpy as np

import phantom

#: The files whose code the kernels are compiled from: the build's key, and what invalidates numba's cache.
SOURCES = tuple(Path(__file__).resolve().parent / name for name in ("kernels.py", "materials.py"))


def sources_digest() -> str:
    """sha256 of :data:`SOURCES`' contents."""
    digest = hashlib.sha256()
    for source in SOURCES:
        digest.update(source.read_bytes())
    return digest.hexdigest()


def compiled_kernels_path() -> Path:
    """Where the ahead-of-time build of the kernels goes: keyed by their sources, numpy's and Python's versions."""
    digest = hashlib.sha256(sources_digest().encode())
    digest.update(f"{np.__version__} {sys.version} {sys.platform}".encode())
    return phantom.cache_dir("kernels") / f"phantom_kernels_{digest.hexdigest()[:16]}.so"


def _load_compiled() -> ModuleType | None:
    """The ahead-of-time build of the kernels when it exists for these sources (else None): calling it needs
    neither numba's import (0.2 s) nor its first-call start (0.4 s), which a CLI call would otherwise pay."""
    path = compiled_kernels_path()
    if os.environ.get("PHANTOM_JIT_KERNELS") or not path.is_file():
        return None
    spec = importlib.util.spec_from_file_location(path.name.split(".")[0], path)
    if spec is None or spec.loader is None:
        return None
    try:
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    except (ImportError, OSError):
        return None
    return module


#: The ahead-of-time build in use, or None (the kernels are numba's JIT).
COMPILED = _load_compiled()
#: Every JIT dispatcher :func:`kernel` made (empty with the ahead-of-time build).
DISPATCHERS: list[Any] = []
if COMPILED is None:
    # numba's cache is the one in NUMBA_CACHE_DIR when the environment names one (a parent process set it)
    NUMBA_CACHE = Path(os.environ.setdefault("NUMBA_CACHE_DIR", str(phantom.cache_dir("numba"))))
    import numba

    _jit = numba.njit(cache=True)
    _jit_inline = numba.njit(cache=True, inline="always")

_announced = False


def _announce_compiling(building: bool) -> None:
    """Say once that numba is about to compile (unless this process is the ahead-of-time build, which says so)."""
    global _announced
    if not _announced and not building:
        print("phantom: compiling the model's kernels with numba (about 10 s, once: they are cached; "
              "`python -m phantom.model.fem.kernels` builds them ahead of time)", file=sys.stderr, flush=True)
    _announced = True


Kernel = TypeVar("Kernel", bound=Callable[..., Any])


def kernel(function: Kernel) -> Kernel:
    """numba's JIT of ``function`` (cached on disk); with the ahead-of-time build loaded, the Python source as it
    is (the build replaces the exported kernels). Either way the kernel takes the same arguments."""
    if COMPILED is not None:
        return function
    dispatcher = _jit(function)
    DISPATCHERS.append(dispatcher)
    return cast(Kernel, dispatcher)


def inline_kernel(function: Kernel) -> Kernel:
    """:func:`kernel`, inlined by numba into each kernel that calls it: for the small per-element pieces (the
    deformation gradient, a law), which as calls cost the 4-node force pass a fifth of its time (0.85 ms against
    0.67 ms written inline, 7308 elements)."""
    if COMPILED is not None:
        return function
    dispatcher = _jit_inline(function)
    DISPATCHERS.append(dispatcher)
    return cast(Kernel, dispatcher)


def forget_stale_jit_cache(building: bool = False) -> None:
    """Empty numba's on-disk cache of every kernel when :data:`SOURCES` changed since it was written, and say once
    that numba is about to compile when the cache holds no kernels or stale ones (``building``: this process is the
    ahead-of-time build, which says so itself). The kernels' module calls it as it is imported.

    numba keys a function's cache by its own file only, but a kernel compiles in the laws it calls from
    materials.py: after an edit of that file numba would load the old laws. A stamp of both files' digest beside
    the cache (one per source folder: worktrees share the cache) says whether the entries are still theirs.
    """
    if COMPILED is not None:
        return
    folder = hashlib.sha256(str(SOURCES[0].parent).encode()).hexdigest()[:16]
    stamp = NUMBA_CACHE / f"phantom_fem_sources_{folder}.sha256"
    digest = sources_digest()
    cached = any(NUMBA_CACHE.rglob("kernels.internal_forces-*.nbi"))
    try:
        if stamp.read_text() == digest:
            if not cached:
                _announce_compiling(building)
            return
    except OSError:
        pass
    _announce_compiling(building)
    for dispatcher in DISPATCHERS:
        dispatcher._cache.flush()  # numba's own index reset: its next call compiles and saves again
    stamp.parent.mkdir(parents=True, exist_ok=True)
    stamp.write_text(digest)
