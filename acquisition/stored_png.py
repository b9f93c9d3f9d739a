"""The pixels of an uncompressed 8-bit grey PNG (as ``synth --images`` writes it) without libpng.

Such a file holds the rows as they are: its zlib stream is "stored" blocks, each row led by
filter byte 0. libpng still runs inflate, Adler-32 and the chunk CRCs over every byte (1.5-1.8
CPU-ms per 1280x720 frame, more than the blob detection); copying the rows out costs ~0.2.
Anything else (deflated, filtered, interlaced, colour, 16-bit, other chunks) returns None and is
left to OpenCV. The checksums are not verified (as stb_image and browsers' decoders skip them):
a flipped bit changes one pixel value; a cut or malformed file still returns None.
"""

from __future__ import annotations

import struct

import numpy as np

SIGNATURE = b"\x89PNG\r\n\x1a\n"
_CHUNK = struct.Struct(">I4s")
_IHDR = struct.Struct(">IIBBBBB")  # width, height, bit depth, colour type, compression, filter, interlace
_STORED = struct.Struct("<BHH")  # block header byte, LEN, NLEN


def stored_size(head: bytes) -> tuple[int, int] | None:
    """``(width, height)`` px when the first 33 bytes of a file are a PNG signature and an IHDR
    of an 8-bit grey, non-interlaced image (the kind :func:`read_stored` may read), else None."""
    if len(head) < 33 or head[:8] != SIGNATURE or _CHUNK.unpack_from(head, 8) != (13, b"IHDR"):
        return None
    width, height, *kind = _IHDR.unpack_from(head, 16)
    return (width, height) if kind == [8, 0, 0, 0, 0] and width and height else None


def read_stored(data: memoryview, out: np.ndarray, rows: np.ndarray) -> bool:
    """Copy the pixels of the PNG file ``data`` into ``out (H, W)`` uint8 (its size from
    :func:`stored_size`), using ``rows (H, W + 1)`` uint8 as scratch; False (``out`` undefined)
    when the file is not a complete stored, unfiltered PNG of that size."""
    height, width = out.shape
    pieces = _idat_pieces(data)
    if pieces is None:
        return False
    stream = _Stream(data, pieces)
    zlib_header = stream.read(2)
    if zlib_header is None or zlib_header[0] & 0x0F != 8 or zlib_header[1] & 0x20 \
            or (zlib_header[0] << 8 | zlib_header[1]) % 31:
        return False
    target, filled, last = memoryview(rows.reshape(-1)), 0, False
    while not last:
        header = stream.read(_STORED.size)
        if header is None:
            return False
        kind, length, check = _STORED.unpack(header)
        if kind & 0b110 or length ^ check != 0xFFFF or filled + length > len(target):
            return False  # a compressed block, or a bad length
        if not stream.copy(length, target[filled:filled + length]):
            return False
        filled, last = filled + length, bool(kind & 1)
    if filled != len(target) or rows[:, 0].any():  # short, or a row with a filter
        return False
    np.copyto(out, rows[:, 1:])
    return True


def _idat_pieces(data: memoryview) -> list[tuple[int, int]] | None:
    """``(start, end)`` byte offsets of each IDAT chunk's data; None when the file holds another
    chunk than IHDR / IDAT / IEND, or is cut."""
    pieces, at = [], len(SIGNATURE)
    while at + 12 <= len(data):
        length, kind = _CHUNK.unpack_from(data, at)
        start, end = at + 8, at + 8 + length
        if end + 4 > len(data) or kind not in (b"IHDR", b"IDAT", b"IEND"):
            return None
        if kind == b"IEND":
            return pieces
        if kind == b"IDAT":
            pieces.append((start, end))
        at = end + 4  # past the CRC
    return None


class _Stream:
    """The zlib stream, read across the IDAT chunks it is split into."""

    def __init__(self, data: memoryview, pieces: list[tuple[int, int]]) -> None:
        self._data, self._pieces, self._index = data, pieces, 0
        self._at = pieces[0][0] if pieces else 0

    def copy(self, count: int, target: memoryview) -> bool:
        """The next ``count`` bytes into ``target``; False when the stream ends first."""
        done = 0
        while done < count:
            if self._index == len(self._pieces):
                return False
            end = self._pieces[self._index][1]
            take = min(count - done, end - self._at)
            target[done:done + take] = self._data[self._at:self._at + take]
            done, self._at = done + take, self._at + take
            if self._at == end:
                self._index += 1
                self._at = self._pieces[self._index][0] if self._index < len(self._pieces) else 0
        return True

    def read(self, count: int) -> bytearray | None:
        out = bytearray(count)
        return out if self.copy(count, memoryview(out)) else None
