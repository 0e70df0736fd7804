"""Byte-level framing: CRC-16/MCRF4XX and COBS (consistent overhead byte stuffing)."""

from phantom.protocol.errors import ProtocolError


def crc16_mcrf4xx(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/MCRF4XX of ``data``: polynomial 0x1021 reflected (0x8408), init 0xFFFF, no final xor.

    The same as avr-libc's ``_crc_ccitt_update`` folded over the bytes; ``b"123456789"`` gives 0x6F91.
    """
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0x8408 if crc & 1 else crc >> 1
    return crc


def cobs_encode(data: bytes) -> bytes:
    """COBS-encode ``data``: the result holds no 0x00 and is at most len(data) // 254 + 1 bytes longer."""
    out = bytearray()
    block = bytearray()
    for byte in data:
        if byte == 0:
            out.append(len(block) + 1)
            out += block
            block.clear()
        else:
            block.append(byte)
            if len(block) == 254:
                out.append(255)
                out += block
                block.clear()
    out.append(len(block) + 1)
    out += block
    return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    """Undo :func:`cobs_encode`; raise ProtocolError on a 0x00 inside or a code that runs past the end."""
    out = bytearray()
    index = 0
    while index < len(data):
        code = data[index]
        if code == 0:
            raise ProtocolError(f"COBS: 0x00 inside an encoded frame at byte {index}")
        end = index + code
        if end > len(data):
            raise ProtocolError(f"COBS: code {code} at byte {index} runs past the end ({len(data)} bytes)")
        block = data[index + 1 : end]
        if 0 in block:
            raise ProtocolError(f"COBS: 0x00 inside an encoded frame after byte {index}")
        out += block
        index = end
        if code != 255 and index < len(data):
            out.append(0)
    return bytes(out)
