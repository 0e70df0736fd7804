"""The design step's user errors."""

from __future__ import annotations

from phantom import PhantomError


class DesignError(PhantomError):
    """Bad input to ``phantom design``: a mask that is not one gland, a volume the walls cannot give chambers at."""
