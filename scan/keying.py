"""Each picture's silhouette keyed as the capture takes it, kept in this process for the reconstruction that
follows (the daemon's verify scan: its capture and its reconstruction run in one scan worker process,
``phantom.host.scan_worker``).

Keying is a third of a verify scan's reconstruction (60 pictures of 640x480, the plan of then: 1.6 s of 5 s idle)
and needs nothing but its own picture, so the capture's pictures thread keys each one after writing it, while the
rig moves to the next stop; after the last picture only the carving and the surface remain. The silhouette is keyed
from the very array written losslessly to the PNG, so it is the one :func:`phantom.scan.reconstruct.reconstruct`
finds reading the PNG back: the volume is the same to the last digit (``tests/test_scan_keying.py``).

Nothing half-done is read later: one capture's silhouettes are kept at a time (a new capture drops the last
one's), a capture that did not complete has them dropped, a picture whose keying failed has none (the
reconstruction keys it again and says why), and :meth:`KeyedPictures.take` hands out only those of a complete
capture whose PNG holds the very bytes that were keyed (their digest), once.
"""

from __future__ import annotations

import hashlib
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from phantom import PhantomError
from phantom.scan.capture import CaptureFolder, Frame
from phantom.scan.silhouette import Silhouette, silhouette


@dataclass(frozen=True)
class _Keyed:
    silhouette: Silhouette
    #: the PNG's digest when it was keyed
    digest: bytes


def _digest(path: Path) -> bytes | None:
    """The file's digest (BLAKE2b, 16 bytes; 60 pictures of 640x480 in about 30 ms), None if it cannot be read."""
    try:
        return hashlib.blake2b(path.read_bytes(), digest_size=16).digest()
    except OSError:
        return None


class KeyedPictures:
    """The silhouettes of the capture under way or last taken in this process (see the module docstring)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._folder: Path | None = None
        self._keyed: dict[str, _Keyed] = {}

    def start(self, folder: CaptureFolder) -> Callable[[Frame, np.ndarray], None]:
        """Keep the silhouettes of ``folder``'s capture from now on (another capture's are dropped): the capture's
        ``keep``, called with each picture once it is written."""
        path = folder.path.resolve()
        with self._lock:
            self._folder, self._keyed = path, {}
        return lambda frame, picture: self._add(path, frame, picture)

    def _add(self, path: Path, frame: Frame, picture: np.ndarray) -> None:
        if picture.dtype != np.uint8 or picture.ndim != 3 or picture.shape[2] != 3:
            return  # not what the PNG reads back as: the reconstruction keys the file
        digest = _digest(path / frame.image)
        if digest is None:
            return  # the file cannot be read back: the reconstruction keys it, or says why not
        try:
            found = silhouette(np.ascontiguousarray(picture))
        except PhantomError:
            return  # the reconstruction keys it again and says what is wrong with it
        with self._lock:
            if self._folder == path:
                self._keyed[frame.image] = _Keyed(found, digest)

    def drop(self, folder: CaptureFolder) -> None:
        """Forget ``folder``'s silhouettes (its capture stopped or aborted)."""
        with self._lock:
            if self._folder == folder.path.resolve():
                self._folder, self._keyed = None, {}

    def take(self, folder: CaptureFolder) -> dict[str, Silhouette]:
        """The silhouettes kept of ``folder``'s pictures, by picture (``Frame.image``), for a complete capture and
        pictures unchanged since they were keyed ({} otherwise); forgotten here."""
        with self._lock:
            if self._folder != folder.path.resolve():
                return {}
            keyed, self._folder, self._keyed = self._keyed, None, {}
        if folder.status != "complete":
            return {}
        return {frame.image: kept.silhouette for frame in folder.frames
                if (kept := keyed.get(frame.image)) is not None
                and kept.digest == _digest(folder.path / frame.image)}


#: This process's: the daemon's scan worker keys its verify scans' pictures here and reconstructs from it.
KEYED = KeyedPictures()
