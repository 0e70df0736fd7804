"""The table files a scene ships (``[model] table_volumes``, ``table_shapes``: ``.npz`` archives that
:mod:`phantom.model.fidelity.response_table` writes), read at the door.

Only the arrays a table uses are read (an unused member costs nothing, however large), each one's size is known
from the zip's directory and its shape and dtype from its ``.npy`` header before its data is read, and every
array is checked against what it must be for the model (shape, dtype, finiteness). A file that is not such an
archive, or whose arrays are not what they must be, is a :class:`SceneError` (exit status 2, which the daemon's
systemd unit does not restart on) that names the file, what is wrong and how to make it again.
"""

from __future__ import annotations

import json
import math
import stat
import tokenize
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from phantom import PhantomError
from phantom.model.errors import SceneError

#: The largest table file read, and the largest array in one (bytes, uncompressed): a shipped volumes file is
#: 9 KB, a shapes file 0.3 MB (19 modes of 1718 nodes).
MAX_TABLE_FILE_BYTES = 64 * 2**20
MAX_MEMBER_BYTES = 256 * 2**20


@dataclass(frozen=True)
class Member:
    """What one array of a table file must be: its shape (None: any length along that axis) and the dtype kinds
    accepted (``"f"`` floats, ``"i"`` integers, ``"U"`` text); floats must be finite."""

    shape: tuple[int | None, ...]
    kinds: str = "f"


def table_members(n_chambers: int, points_per_axis: int, shapes: bool) -> dict[str, Member]:
    """The arrays a table file holds for a model of ``n_chambers`` on ``points_per_axis`` points per chamber's
    pressure axis: the volumes file's, and with ``shapes`` the shapes file's too (its modes and nodes any
    number)."""
    grid = (points_per_axis,) * n_chambers
    members = {"chamber": Member((*grid, n_chambers)), "gland": Member(grid), "check_errors_pct": Member(()),
               "build_time_s": Member(()), "rest_volumes_m3": Member((n_chambers + 1,))}
    if shapes:
        members.update({"coefficients": Member((*grid, None)), "modes_m": Member((None, None, 3)),
                        "nodes": Member((None,), "iu"), "rest_positions_m": Member((None, 3)),
                        "check_error_m": Member(())})
    return members


def read_provenance(path: Path, where: str, remedy: str) -> dict[str, Any]:
    """The model a table file was made for (its ``provenance`` member, a JSON object)."""
    text = read_members(path, {"provenance": Member((), "U")}, where, remedy)["provenance"]
    try:
        provenance = json.loads(str(text))
    except (ValueError, RecursionError):
        provenance = None
    if not isinstance(provenance, dict):
        raise SceneError(f"{where} is damaged (its provenance is not a JSON object): {remedy}")
    return provenance


def read_members(path: Path, members: dict[str, Member], where: str, remedy: str,
                 error: type[PhantomError] = SceneError,
                 max_file_bytes: int = MAX_TABLE_FILE_BYTES) -> dict[str, np.ndarray]:
    """The arrays ``members`` names from the ``.npz`` at ``path`` (at most ``max_file_bytes``), each checked
    against its :class:`Member` before (shape, dtype, size from the headers) and after (finiteness) its data is
    read; ``error`` otherwise. (Other parts read their own archives of arrays with it: a shape run's checkpoint.)"""
    try:
        return _read_members(path, members, where, remedy, max_file_bytes)
    except SceneError as refusal:
        if error is SceneError:
            raise
        raise error(str(refusal)) from None


def _read_members(path: Path, members: dict[str, Member], where: str, remedy: str,
                  max_file_bytes: int) -> dict[str, np.ndarray]:
    try:
        info = path.stat()
    except OSError as error:
        raise SceneError(f"{where} cannot be read ({error.strerror}): {remedy}") from None
    if not stat.S_ISREG(info.st_mode) or info.st_size > max_file_bytes:
        raise SceneError(f"{where} is not one of ours (a regular file of at most {max_file_bytes // 2**20} MiB): "
                         f"{remedy}")
    try:
        with zipfile.ZipFile(path) as archive:
            return {name: _member(archive, name, member, where, remedy) for name, member in members.items()}
    except (zipfile.BadZipFile, zipfile.LargeZipFile, zlib.error, OSError, EOFError, ValueError, NotImplementedError,
            SyntaxError, tokenize.TokenError) as error:  # a damaged directory, stream, CRC or .npy header (parsed
        # as a Python literal: numpy tokenizes an old header first, whose unclosed bracket is a TokenError)
        text = " ".join(str(error).split())
        raise SceneError(f"{where} is damaged ({type(error).__name__}: {text}): {remedy}") from None


def _member(archive: zipfile.ZipFile, name: str, member: Member, where: str, remedy: str) -> np.ndarray:
    try:
        entry = archive.getinfo(f"{name}.npy")
    except KeyError:
        raise SceneError(f"{where} is damaged (it has no array {name!r}): {remedy}") from None
    if entry.file_size > MAX_MEMBER_BYTES:
        raise SceneError(f"{where} is damaged (its array {name!r} is {entry.file_size / 2**20:.0f} MiB, more than "
                         f"the {MAX_MEMBER_BYTES // 2**20} MiB of any table's): {remedy}")
    with archive.open(entry) as stream:
        version = np.lib.format.read_magic(stream)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(stream)
        elif version == (2, 0):
            shape, _, dtype = np.lib.format.read_array_header_2_0(stream)
        else:
            raise ValueError(f"npy format {version} of {name!r} is not one a table is written in")
    fits = len(shape) == len(member.shape) and all(
        want is None or want == have for want, have in zip(member.shape, shape, strict=True))
    if dtype.hasobject or dtype.kind not in member.kinds or not fits:
        wanted = " x ".join("any" if side is None else str(side) for side in member.shape) or "a scalar"
        raise SceneError(f"{where} is damaged (its array {name!r} is {dtype} of shape {shape}, not {wanted} of kind "
                         f"{member.kinds!r}: made for another model or grid): {remedy}")
    if math.prod(shape) * dtype.itemsize > entry.file_size:
        raise SceneError(f"{where} is damaged (its array {name!r} declares {shape} but holds {entry.file_size} "
                         f"bytes): {remedy}")
    with archive.open(entry) as stream:
        array: np.ndarray = np.lib.format.read_array(stream, allow_pickle=False)
    if array.dtype.kind == "f" and not np.all(np.isfinite(array)):
        raise SceneError(f"{where} is damaged (its array {name!r} holds NaN or infinite values): {remedy}")
    return array


def check_shape_nodes(arrays: dict[str, np.ndarray], where: str, remedy: str) -> None:
    """The shapes file's arrays agree with each other: as many modes in the coefficients as in ``modes_m``, one
    node each for ``modes_m`` and ``rest_positions_m``, nodes sorted, distinct and not negative."""
    nodes, modes = arrays["nodes"], arrays["modes_m"]
    consistent = (arrays["coefficients"].shape[-1] == modes.shape[0] and modes.shape[1] == len(nodes)
                  == len(arrays["rest_positions_m"]) and len(nodes) > 0)
    if not consistent or nodes.min() < 0 or np.any(np.diff(nodes) <= 0):
        raise SceneError(f"{where} is damaged (its nodes, modes and rest positions do not agree, or the nodes are "
                         f"not distinct, sorted, non-negative indices): {remedy}")
