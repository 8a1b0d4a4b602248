"""Checksums used by serial tracker protocols.

CRC-16/ARC is the NDI Combined API checksum (polynomial x^16 + x^15 + x^2 + 1, i.e. 0x8005, processed
bit-reversed as 0xA001; initial value 0; no final XOR). ``binascii.crc_hqx`` is CRC-16/XMODEM, a different CRC.
"""

from __future__ import annotations

import functools
import operator


def _arc_of_byte(crc: int) -> int:
    for _ in range(8):
        crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


_ARC_TABLE = tuple(_arc_of_byte(byte) for byte in range(256))


def crc16_arc(data: bytes) -> int:
    """CRC-16/ARC of ``data`` as an int in [0, 0xFFFF].

    >>> hex(crc16_arc(b"123456789"))
    '0xbb3d'
    >>> f"{crc16_arc(b'INIT:'):04X}"
    'E3A5'
    """
    crc = 0
    for byte in bytes(data):
        crc = (crc >> 8) ^ _ARC_TABLE[(crc ^ byte) & 0xFF]
    return crc


def xor8(data: bytes) -> int:
    """XOR of all bytes (the NMEA 0183 sentence checksum, computed between '$' and '*').

    >>> f"{xor8(b'GPGLL,4916.45,N,12311.12,W,225444,A'):02X}"
    '31'
    """
    return functools.reduce(operator.xor, bytes(data), 0)
