"""The model's user-facing errors: each says what was wrong and what to do."""

from phantom import PhantomError


class SceneError(PhantomError):
    """A scene file that cannot be read or says something the model cannot do."""


class MeshError(PhantomError):
    """A mesh that cannot be generated, read, or used: missing groups, open walls, bad tetrahedra."""


class SolveError(PhantomError):
    """A solve that did not converge or inverted elements; the message names the chamber and pressure."""
