"""The protocol's error type."""

from phantom import PhantomError


class ProtocolError(PhantomError):
    """A frame or message that breaks the wire protocol: the message says which rule and what was seen."""
