"""The shape analysis's user errors."""

from __future__ import annotations

from phantom import PhantomError


class ShapeError(PhantomError):
    """Bad input to the shape analysis: a missing label, an empty mask, an open mesh, a run without a checkpoint."""
