"""Images one after another in a byte stream: the frames a pipeline writes to a pipe.

``ffmpeg -i CAMERA -f image2pipe -c:v mjpeg -`` (or ``-c:v png``, ``ppm``, ``pgm``, ``bmp``)
writes encoded images back to back, with nothing between them.  :func:`split_images` cuts such a
stream into one ``bytes`` object per image by walking each format's own structure:

* **JPEG**: marker segments (each with its length) up to a start of scan, then the entropy-coded
  data up to the next marker that is not a stuffed ``FF 00`` or a restart marker, repeated
  (progressive JPEGs have several scans) until the end-of-image marker.  Markers inside segments
  (an EXIF thumbnail's own end-of-image) are skipped with their segment.
* **PNG**: the signature, then chunks (length, type, data, CRC) up to ``IEND``.
* **PNM** (``P5`` grey, ``P6`` colour): the header's width, height and maximum value give the
  size of the pixel data.
* **BMP**: the file size in its header.

Bytes that start no known image (a corrupt or cut frame) are skipped up to the next JPEG or PNG
signature; each skip is reported to ``on_skip(byte_count)``.  Nothing here decodes pixels
(:func:`fr_torch.images.io.decode_image_bytes` does, with its limits); an image is held whole in
memory, so a declared size above :data:`fr_torch.images.io.MAX_FILE_BYTES` is skipped as corrupt.
"""
from __future__ import annotations

import re
import struct
from typing import Callable, Iterator

from fr_torch.images.io import MAX_FILE_BYTES

JPEG_START = b"\xff\xd8\xff"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: Where a new image may start after corrupt bytes (PNM and BMP signatures are too short to trust).
_RESYNC = re.compile(re.escape(JPEG_START) + b"|" + re.escape(PNG_SIGNATURE))
_PNM_HEADER = re.compile(rb"P([56])(?:\s+|#[^\n]*\n)+(\d+)(?:\s+|#[^\n]*\n)+(\d+)(?:\s+|#[^\n]*\n)+(\d+)\s")


class NotAnImage(ValueError):
    """The bytes at the start of the buffer are no image of a known format (or a corrupt one)."""


def image_length(data: bytes | bytearray) -> int | None:
    """Length in bytes of the complete image at the start of ``data``; None when ``data`` ends
    before the image does (more bytes needed).  Raises :class:`NotAnImage` for bytes that start
    no image of a known format, or a structure that cannot be one."""
    if data[:3] == JPEG_START:
        return _jpeg_length(data)
    if data[:8] == PNG_SIGNATURE:
        return _png_length(data)
    if data[:1] == b"P" and data[1:2] in (b"5", b"6"):
        return _pnm_length(data)
    if data[:2] == b"BM":
        if len(data) < 6:
            return None
        return _bounded(struct.unpack("<I", data[2:6])[0], minimum=26)
    if len(data) < 2 or (len(data) < 8 and (PNG_SIGNATURE.startswith(bytes(data)) or JPEG_START.startswith(bytes(data)))):
        return None
    raise NotAnImage("no JPEG, PNG, PNM or BMP signature")


def _bounded(length: int, minimum: int = 1) -> int:
    if not minimum <= length <= MAX_FILE_BYTES:
        raise NotAnImage(f"declared image length {length} bytes")
    return length


def _jpeg_length(data: bytes | bytearray) -> int | None:
    pos, size = 2, len(data)
    while True:
        if pos + 2 > size:
            return None
        if data[pos] != 0xFF:
            raise NotAnImage(f"JPEG: no marker at byte {pos}")
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker == 0xD9:  # end of image
            return pos + 2
        if marker in (0x01, 0xD8) or 0xD0 <= marker <= 0xD7:  # standalone markers
            pos += 2
            continue
        if pos + 4 > size:
            return None
        length = struct.unpack(">H", data[pos + 2:pos + 4])[0]
        if length < 2:
            raise NotAnImage(f"JPEG: segment length {length} at byte {pos}")
        pos += 2 + length
        _bounded(pos)
        if marker != 0xDA:  # a start of scan is followed by entropy-coded data up to the next marker
            continue
        while True:
            pos = data.find(b"\xff", pos)
            if pos < 0 or pos + 1 >= size:
                return None
            following = data[pos + 1]
            if following == 0x00 or 0xD0 <= following <= 0xD7:  # stuffed byte, restart marker
                pos += 2
                continue
            break


def _png_length(data: bytes | bytearray) -> int | None:
    pos = 8
    while True:
        if pos + 8 > len(data):
            return None
        length, kind = struct.unpack(">I4s", data[pos:pos + 8])
        pos += 12 + length
        _bounded(pos)
        if kind == b"IEND":
            return pos if pos <= len(data) else None


def _pnm_length(data: bytes | bytearray) -> int | None:
    match = _PNM_HEADER.match(data)
    if match is None:
        if len(data) < 64:
            return None
        raise NotAnImage("PNM: unreadable header")
    channels = 3 if match.group(1) == b"6" else 1
    width, height, maxval = (int(match.group(k)) for k in (2, 3, 4))
    if not (width and height and 0 < maxval < 65536):
        raise NotAnImage(f"PNM: header {width} x {height}, maximum {maxval}")
    return _bounded(match.end() + width * height * channels * (1 if maxval < 256 else 2))


def split_images(read: Callable[[int], bytes], on_skip: Callable[[int], None] | None = None,
                 chunk_size: int = 1 << 16) -> Iterator[bytes]:
    """Yield the images of a byte stream one by one, as they complete, until it ends; corrupt
    bytes are skipped (``on_skip(count)``) up to the next image signature, and so is a cut image
    at the end.  ``read(n)``: up to ``n`` bytes, as soon as some are there (``os.read`` of a
    pipe's descriptor, a file's ``read1``); empty at the end."""
    buffer = bytearray()
    ended = False
    while True:
        while buffer:
            try:
                length = image_length(buffer)
            except NotAnImage:
                found = _RESYNC.search(buffer, 1)
                skipped = found.start() if found else len(buffer)
                del buffer[:skipped]
                if on_skip is not None:
                    on_skip(skipped)
                continue
            if length is None or length > len(buffer):
                break
            yield bytes(buffer[:length])
            del buffer[:length]
        if ended:
            if buffer and on_skip is not None:
                on_skip(len(buffer))
            return
        more = read(chunk_size)
        if not more:
            ended = True
        else:
            buffer += more
