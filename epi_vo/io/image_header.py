"""The size an encoded image declares in its header, read without decoding it (no rclpy).

A CompressedImage of ROS's compressed transport is a JPEG or a PNG. Decoding allocates what the header
declares, whatever the payload's own size: a 0.9 MB PNG of one colour can declare 30000 x 30000 pixels and
take gigabytes to decode. :func:`declared_size` reads width and height from the PNG IHDR chunk or the JPEG
start-of-frame segment so that a caller can refuse the image before it is decoded.

References: PNG (ISO/IEC 15948) section 11.2.2, IHDR; JPEG (ITU-T T.81) annex B.2 (marker segments, frame
header SOFn: P, Y, X after the length).
"""

from __future__ import annotations

import struct
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
JPEG_SOI = b"\xff\xd8"
# SOF0..SOF15 carry the frame size, except DHT (C4), JPG (C8) and DAC (CC), which share the range.
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
# Markers without a length field: TEM, RST0..7 (SOI and EOI end the scan below).
_JPEG_STANDALONE = frozenset({0x01, *range(0xD0, 0xD8)})


class DeclaredSize(NamedTuple):
    """Width and height in pixels as the header declares them, and the format that declares them."""

    width: int
    height: int
    format: str  # "png" or "jpeg"


def declared_size(data: NDArray[np.uint8]) -> DeclaredSize | str:
    """The size the JPEG or PNG in ``data`` declares, or why there is none (a one-line reason: not a JPEG or
    PNG, header cut short, no frame header before the image data). Reads only the header."""
    head = bytes(data[:8])
    if head == PNG_SIGNATURE:
        return _png_size(data)
    if head[:2] == JPEG_SOI:
        return _jpeg_size(data)
    return "the payload is neither a JPEG nor a PNG (the formats of ROS's compressed image transport)"


def _png_size(data: NDArray[np.uint8]) -> DeclaredSize | str:
    # Signature, then the IHDR chunk first: length (4), type 'IHDR' (4), width (4), height (4), big-endian.
    if data.size < 24 or bytes(data[12:16]) != b"IHDR":
        return "the PNG has no IHDR chunk after its signature"
    width, height = struct.unpack(">II", bytes(data[16:24]))
    return DeclaredSize(width, height, "png")


def _jpeg_size(data: NDArray[np.uint8]) -> DeclaredSize | str:
    i = 2
    n = int(data.size)
    while i + 4 <= n:
        if data[i] != 0xFF:
            return f"the JPEG has no marker at byte {i} before its frame header"
        marker = int(data[i + 1])
        if marker == 0xFF:  # fill byte before a marker
            i += 1
            continue
        if marker in _JPEG_STANDALONE:
            i += 2
            continue
        if marker in (0xD8, 0xD9, 0xDA):  # SOI again, EOI or the scan: no frame header came first
            break
        length = (int(data[i + 2]) << 8) | int(data[i + 3])
        if marker in _JPEG_SOF:
            if i + 9 > n or length < 7:
                return "the JPEG frame header is cut short"
            height = (int(data[i + 5]) << 8) | int(data[i + 6])
            width = (int(data[i + 7]) << 8) | int(data[i + 8])
            return DeclaredSize(width, height, "jpeg")
        if length < 2:
            return f"the JPEG segment at byte {i} has length {length}"
        i += 2 + length
    return "the JPEG has no frame header (SOF) before its image data"
