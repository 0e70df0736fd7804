"""The wire protocol between host and firmware: message table, frame codec and streaming reader.

``phantom.protocol.messages`` is generated from ``spec.toml`` (``python -m phantom.protocol.generate``);
``phantom.protocol.codec`` encodes and decodes whole wire frames; PROTOCOL.md describes the bytes.
"""

from phantom.protocol.errors import ProtocolError

__all__ = ["ProtocolError"]
