"""Bounded, hostile-input-safe image decoding and the working resolution of the detector.

Policy (what a file may cost before it is refused or reduced):

* Only **regular files** are opened (a FIFO, a directory or a device is refused without being
  opened for reading, so a named pipe can never hang the process).
* Files larger than :data:`MAX_FILE_BYTES` (default 512 MB, ``FR_MAX_FILE_BYTES``) are refused.
* The **declared size** is read from the header before decoding (PNG IHDR, JPEG SOF, BMP, GIF,
  WebP, TIFF IFD0, PNM); an image declaring more than :data:`MAX_IMAGE_PIXELS` pixels (default
  600 MP, ``FR_MAX_IMAGE_PIXELS``), or a zero size, is refused with that reason.  Formats we
  cannot probe are still bounded by OpenCV's own ``OPENCV_IO_MAX_IMAGE_PIXELS`` (set to the same
  limit here unless the user set it).
* Pixels decoded are bounded: big images are decoded with ``cv2.IMREAD_REDUCED_*`` (native 1/2,
  1/4, 1/8 DCT scaling for JPEG, so a 12-MP photo is decoded at ~1000 px directly), and images
  whose colour buffer would exceed :data:`MAX_COLOR_BYTES` are decoded in grey, so the peak
  decode buffer stays below ~600 MB and the peak RSS per image below ~1 GB.
* Any decoder failure (``cv2.error``, ``None``, whatever exception) becomes a
  :class:`~fr_torch.errors.FRInputError` with a one-line reason; OpenCV's own ``[ WARN ]`` /
  ``[ERROR ]`` log lines are silenced while decoding.
* **EXIF orientation is applied** (OpenCV's ``IMREAD_COLOR`` / ``IMREAD_GRAYSCALE`` default):
  the image is calibrated as a viewer displays it, so roll, tilt and the width / height refer to
  the displayed (upright) picture, not to the sensor's raw pixel rows.

Working resolution: the detector runs on a copy whose long side is at most
:data:`WORKING_LONG_SIDE` pixels (images smaller than that are used as they are; a setting of the
estimator, :func:`parse_working_long_side`).  The estimate is made in working pixels and brought
back (``scale`` = input pixels per working pixel; points map as the resize maps pixels,
:func:`fr_torch.core.geometry.conventions.resize_points`, pixel centres at integers), so results are
always reported in the **input image's pixels**.  The detection's time grows with the working
image's pixels up to the cap; the search keeps a fixed number of the longest segments, so its
time does not.
"""
from __future__ import annotations

import contextlib
import io
import os
import stat
import struct
from pathlib import Path

import numpy as np

from fr_torch.core.geometry.conventions import resize_homogeneous, resize_points
from fr_torch.errors import FRInputError
from fr_torch.images.convert import to_bgr8, to_gray8


def _env_number(name: str, default: float) -> float:
    try:
        value = float(os.environ.get(name, default))
        return value if value > 0 else default
    except ValueError:
        return default


MAX_IMAGE_PIXELS = int(_env_number("FR_MAX_IMAGE_PIXELS", 600e6))
MAX_FILE_BYTES = int(_env_number("FR_MAX_FILE_BYTES", 512 * 2 ** 20))
MAX_COLOR_BYTES = 400 * 2 ** 20  # above this a colour decode would be too big: decode in grey
#: The default cap on the long side (pixels) of the image the lines are detected on: a larger photo
#: is brought down to it, a smaller one is used as it is.
WORKING_LONG_SIDE = 1280
#: The smallest cap :func:`parse_working_long_side` accepts (pixels).
MIN_WORKING_LONG_SIDE = 64
# OpenCV reads this once, at its first decode: bound the formats we cannot probe as well.
os.environ.setdefault("OPENCV_IO_MAX_IMAGE_PIXELS", str(MAX_IMAGE_PIXELS))

import cv2  # noqa: E402  (after the environment variable above)


def _error(message: str):
    return FRInputError(message)


def display_name(path) -> str:
    """A printable name for a path (undecodable bytes shown as ``\\xNN`` escapes)."""
    text = os.fsdecode(path) if isinstance(path, (bytes, os.PathLike)) else str(path)
    return text.encode("utf-8", "backslashreplace").decode("utf-8") if _has_surrogates(text) else text


def _has_surrogates(text: str) -> bool:
    try:
        text.encode("utf-8")
        return False
    except UnicodeEncodeError:
        return True


@contextlib.contextmanager
def quiet_opencv():
    """Silence OpenCV's own log lines (``[ WARN ] ... grfmt_png.cpp``) inside the block."""
    logging = getattr(getattr(cv2, "utils", None), "logging", None)
    if logging is None:
        yield
        return
    previous = logging.getLogLevel()
    logging.setLogLevel(logging.LOG_LEVEL_SILENT)
    try:
        yield
    finally:
        logging.setLogLevel(previous)


# --------------------------------------------------------------------------- header probes

def jpeg_segments(head: bytes, read=None, max_offset: int | None = None):
    """The marker segments of a JPEG, from after its SOI marker to the first start of scan (SOS)
    or end of image (EOI): yields ``(marker, length, body)``, ``length`` the segment's 2-byte
    length field and ``body`` the bytes after it (shorter than ``length - 2`` when the data ends
    first).

    ``head``: the file's first bytes, from SOI on; ``read(n)``: more bytes of the same stream (None:
    ``head`` is all there is).  Fill bytes and standalone markers (TEM, RSTn, a repeated SOI) are
    skipped; the walk stops quietly at a byte that is not a marker, at the end of the data, or at a
    segment starting past ``max_offset`` bytes.
    """
    data, pos = head, 2

    def available(end: int) -> bool:  # read until data holds ``end`` bytes, if the stream has them
        nonlocal data
        while len(data) < end:
            more = read(65536) if read is not None else b""
            if not more:
                return False
            data += more
        return True

    while max_offset is None or pos <= max_offset:
        if not available(pos + 4) or data[pos] != 0xFF:
            return
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker in (0x01, 0xD8) or 0xD0 <= marker <= 0xD7:
            pos += 2
            continue
        if marker in (0xD9, 0xDA):  # end of image / start of scan
            return
        length = struct.unpack(">H", data[pos + 2:pos + 4])[0]
        available(pos + 2 + length)
        yield marker, length, data[pos + 4:pos + 2 + length]
        pos += 2 + length


#: Start-of-frame markers (baseline, progressive, lossless, arithmetic): their body holds the size.
_SOF_MARKERS = (0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF)


def jpeg_header(head: bytes, read=None) -> tuple[tuple[int, int] | None, bool]:
    """((width, height) from the first SOF marker, or None; whether an EXIF APP1 segment before it
    asks for a rotation (orientation other than 1)), walking the segments of :func:`jpeg_segments`
    (``head`` from SOI on, ``read`` for more bytes) only up to that marker (none in the first
    16 MB: None)."""
    rotated = False
    for marker, _, body in jpeg_segments(head, read, max_offset=16 * 2 ** 20):
        if marker == 0xE1 and _exif_orientation(body) != 1:
            rotated = True
        if marker in _SOF_MARKERS:
            if len(body) < 5:
                return None, rotated
            height, width = struct.unpack(">HH", body[1:5])
            return (width, height), rotated
    return None, rotated


def _jpeg_size(head: bytes, handle) -> tuple[int, int] | None:
    """(width, height) from the first SOF marker, reading segment by segment (no SOF in the first
    16 MB: None)."""
    return jpeg_header(head, handle.read)[0]


def _exif_orientation(body: bytes) -> int:
    """EXIF orientation (1-8) of an APP1 segment body, 1 when the body holds none."""
    if not body.startswith(b"Exif\x00\x00") or len(body) < 14:
        return 1
    tiff = body[6:]
    order = "<" if tiff[:2] == b"II" else ">" if tiff[:2] == b"MM" else None
    if order is None:
        return 1
    try:
        ifd = struct.unpack(order + "I", tiff[4:8])[0]
        (entries,) = struct.unpack(order + "H", tiff[ifd:ifd + 2])
        for k in range(entries):
            start = ifd + 2 + 12 * k
            tag, kind = struct.unpack(order + "HH", tiff[start:start + 4])
            if tag == 0x0112 and kind == 3:  # Orientation, SHORT
                return struct.unpack(order + "H", tiff[start + 8:start + 10])[0]
    except struct.error:
        return 1
    return 1


def _tiff_size(head: bytes, handle) -> tuple[int, int] | None:
    order = "<" if head[:2] == b"II" else ">"
    (offset,) = struct.unpack(order + "I", head[4:8])
    handle.seek(offset)
    raw = handle.read(2)
    if len(raw) < 2:
        return None
    (count,) = struct.unpack(order + "H", raw)
    entries = handle.read(12 * min(count, 4096))
    size = {}
    for k in range(len(entries) // 12):
        tag, kind, _, value = struct.unpack(order + "HHI4s", entries[12 * k:12 * k + 12])
        if tag in (256, 257):
            size[tag] = struct.unpack(order + ("H" if kind == 3 else "I"), value[:2 if kind == 3 else 4])[0]
    return (size[256], size[257]) if len(size) == 2 else None


def _pnm_size(head: bytes) -> tuple[int, int] | None:
    tokens, text = [], head[2:].split(b"\n")
    for line in text:
        tokens += line.split(b"#", 1)[0].split()
        if len(tokens) >= 2:
            try:
                return int(tokens[0]), int(tokens[1])
            except ValueError:
                return None
    return None


def probe_image_size(path) -> tuple[int, int] | None:
    """Declared (width, height) from the file header, before any decoding; None when unknown.

    Reads a few bytes (JPEG: marker segments up to the first SOF).  Width / height are the stored
    ones (before EXIF orientation).  Raises nothing for odd files: a header we cannot parse is None.
    """
    try:
        with open(path, "rb") as handle:
            return header_size(handle)
    except OSError:
        return None


def header_size(handle) -> tuple[int, int] | None:
    """:func:`probe_image_size` of an open binary stream positioned at the image's first byte (a
    file, or ``io.BytesIO`` of an image held in memory)."""
    try:
        head = handle.read(64)
        if head.startswith(b"\x89PNG\r\n\x1a\n") and head[12:16] == b"IHDR":
            return struct.unpack(">II", head[16:24])
        if head.startswith(b"\xff\xd8"):
            return _jpeg_size(head, handle)
        if head.startswith(b"BM") and len(head) >= 26:
            width, height = struct.unpack("<ii", head[18:26])
            return abs(width), abs(height)
        if head[:6] in (b"GIF87a", b"GIF89a"):
            return struct.unpack("<HH", head[6:10])
        if head[:4] == b"RIFF" and head[8:12] == b"WEBP":
            chunk = head[12:16]
            if chunk == b"VP8X":
                return (int.from_bytes(head[24:27], "little") + 1, int.from_bytes(head[27:30], "little") + 1)
            if chunk == b"VP8L":
                bits = int.from_bytes(head[21:25], "little")
                return (bits & 0x3FFF) + 1, ((bits >> 14) & 0x3FFF) + 1
            if chunk == b"VP8 ":
                width, height = struct.unpack("<HH", head[26:30])
                return width & 0x3FFF, height & 0x3FFF
            return None
        if head[:4] in (b"II*\x00", b"MM\x00*"):
            return _tiff_size(head, handle)
        if head[:1] == b"P" and head[1:2] in b"123456" and len(head) > 3:
            return _pnm_size(head + handle.read(960))
    except (OSError, struct.error, ValueError, KeyError):
        return None
    return None


# --------------------------------------------------------------------------- decoding

_REDUCED_COLOR = {1: cv2.IMREAD_COLOR, 2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4,
                  8: cv2.IMREAD_REDUCED_COLOR_8}
_REDUCED_GRAY = {1: cv2.IMREAD_GRAYSCALE, 2: cv2.IMREAD_REDUCED_GRAYSCALE_2, 4: cv2.IMREAD_REDUCED_GRAYSCALE_4,
                 8: cv2.IMREAD_REDUCED_GRAYSCALE_8}


def check_regular_file(path) -> os.stat_result:
    """stat() the path and refuse anything but a regular, non-empty, not-too-big file."""
    name = display_name(path)
    try:
        info = os.stat(path)
    except FileNotFoundError:
        raise _error(f"{name}: no such file") from None
    except OSError as exc:
        raise _error(f"{name}: cannot read ({exc.strerror or exc})") from None
    if stat.S_ISDIR(info.st_mode):
        raise _error(f"{name}: is a directory, not an image")
    if not stat.S_ISREG(info.st_mode):
        kind = ("a named pipe (FIFO)" if stat.S_ISFIFO(info.st_mode) else
                "a device" if stat.S_ISCHR(info.st_mode) or stat.S_ISBLK(info.st_mode) else
                "a socket" if stat.S_ISSOCK(info.st_mode) else "not a regular file")
        raise _error(f"{name}: is {kind}, not an image file")
    if info.st_size == 0:
        raise _error(f"{name}: empty file")
    if info.st_size > MAX_FILE_BYTES:
        raise _error(f"{name}: file of {info.st_size / 2 ** 20:.0f} MB is above the {MAX_FILE_BYTES / 2 ** 20:.0f} MB "
                     "limit (FR_MAX_FILE_BYTES)")
    return info


def read_image(path, max_long_side: int | None = None) -> tuple[np.ndarray, tuple[int, int]]:
    """Decode an image file safely (see the module docstring for the limits).

    ``max_long_side``: decode no more than needed for a copy of this long side (pixels; the result
    may be up to 2x larger, or down to 0.9x: the native reductions are 1, 1/2, 1/4, 1/8; None =
    full size, subject only to the memory bound).  Decoded in colour, except a non-JPEG too big
    for the memory bound in colour, which is decoded to one channel.
    Returns (image, (width, height)): an 8-bit grey (H, W) or BGR (H, W, 3) array, and the input's
    size in pixels as displayed (after EXIF orientation), which the array may be a reduction of.
    Raises FRInputError with a one-line reason on any problem.
    """
    name = display_name(path)
    check_regular_file(path)
    return _decode(lambda: np.fromfile(path, dtype=np.uint8), name, probe_image_size(path), _is_jpeg(path),
                   max_long_side)


def decode_image_bytes(data: bytes, name: str, max_long_side: int | None = None) -> tuple[np.ndarray, tuple[int, int]]:
    """:func:`read_image` of an image held in memory (one frame of a stream: JPEG, PNG, PNM, BMP
    ...), with the same limits and the same one-line FRInputError; ``name`` names it in messages."""
    if not data:
        raise _error(f"{name}: empty image")
    if len(data) > MAX_FILE_BYTES:
        raise _error(f"{name}: image of {len(data) / 2 ** 20:.0f} MB is above the {MAX_FILE_BYTES / 2 ** 20:.0f} MB "
                     "limit (FR_MAX_FILE_BYTES)")
    return _decode(lambda: np.frombuffer(data, dtype=np.uint8), name, header_size(io.BytesIO(data)),
                   bytes(data[:2]) == b"\xff\xd8", max_long_side)


def _decode(load, name: str, declared: tuple[int, int] | None, jpeg: bool,
            max_long_side: int | None) -> tuple[np.ndarray, tuple[int, int]]:
    """The bounded decode of :func:`read_image`: ``load()`` gives the encoded bytes (uint8 array),
    ``declared`` the header's (width, height) or None, ``jpeg`` whether it is a JPEG."""
    gray = False
    if declared is not None:
        width, height = (int(v) for v in declared)
        if width <= 0 or height <= 0:
            raise _error(f"{name}: header declares a zero-size image ({width} x {height})")
        if width * height > MAX_IMAGE_PIXELS:
            raise _error(f"{name}: header declares {width} x {height} pixels ({width * height / 1e6:.0f} MP), above "
                         f"the {MAX_IMAGE_PIXELS / 1e6:.0f} MP limit (FR_MAX_IMAGE_PIXELS)")
        factor = 1
        long_side = max(width, height)
        # Slack 0.9: a 4000-px photo decodes at 1/4 (1000 px, native DCT scaling) rather than at 1/2.
        while (factor < 8 and max_long_side is not None and long_side / (2 * factor) >= 0.9 * max_long_side):
            factor *= 2
        # Memory bound for full-size decodes (only JPEG reduces natively; others decode at full size).
        while factor < 8 and width * height * 3 / factor ** 2 > MAX_COLOR_BYTES:
            factor *= 2
        # OpenCV reduces other formats by resizing the full decode, which fails when a side would
        # shrink below one pixel (a 5000 x 1 strip): reduce such an image less.
        while factor > 1 and min(width, height) < factor:
            factor //= 2
        if width * height * 3 > MAX_COLOR_BYTES and not jpeg:
            gray = True
    else:
        factor = 1
    flags = (_REDUCED_GRAY if gray else _REDUCED_COLOR)[factor]
    try:
        data = load()
        with quiet_opencv():
            image = cv2.imdecode(data, flags)
    except MemoryError:
        raise _error(f"{name}: not enough memory to decode this image") from None
    except Exception as exc:  # cv2.error and anything else: this image's failure only
        reason = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
        raise _error(f"{name}: cannot decode image ({reason[:200]})") from None
    if image is None or image.size == 0:
        raise _error(f"{name}: not a readable image (unknown format, truncated or corrupt)")
    h, w = image.shape[:2]
    if declared is None:
        size = (w * factor, h * factor)
    else:
        size = (width, height)
        if (w > h) != (width > height) and w != h and width != height:  # EXIF orientation 5-8 swapped the axes
            size = (height, width)
    return image, size


def _is_jpeg(path) -> bool:
    try:
        with open(path, "rb") as handle:
            return handle.read(2) == b"\xff\xd8"
    except OSError:
        return False


def parse_working_long_side(value, name: str = "working_long_side") -> int | None:
    """The working resolution's cap from a setting: a whole number of pixels >= :data:`MIN_WORKING_LONG_SIDE`
    (an int or its text), or ``None`` / ``"input"`` for the input's own resolution (no cap).
    Anything else is an FRInputError (one line) naming the setting ``name``."""
    if value is None or (isinstance(value, str) and value.strip().lower() == "input"):
        return None
    try:
        number = int(value) if not isinstance(value, float) or float(value).is_integer() else None
    except (TypeError, ValueError):
        number = None
    if isinstance(value, bool) or number is None or number < MIN_WORKING_LONG_SIDE:
        raise FRInputError(f"{name}: expected a whole number of pixels >= {MIN_WORKING_LONG_SIDE} "
                           f"or 'input', got {value!r}")
    return number


def working_size(size: tuple[int, int], max_long_side: int | None = WORKING_LONG_SIDE) -> tuple[int, int]:
    """The (width, height) in pixels an input of ``size`` (width, height) is calibrated at: scaled
    so that its long side is ``max_long_side`` (rounded, at least 1 pixel), or ``size`` itself when
    that is small enough or ``max_long_side`` is None."""
    width, height = size
    long_side = max(width, height)
    if max_long_side is None or long_side <= max_long_side:
        return width, height
    ratio = max_long_side / long_side
    return max(1, round(width * ratio)), max(1, round(height * ratio))


def read_working(image, name: str, max_long_side: int | None = WORKING_LONG_SIDE):
    """Image ``image`` (a path, read by the bounded decoder, or an array) as grey levels at the
    working resolution: (working image (H, W) uint8, input pixels per working pixel, the input's
    (width, height)).  Raises FRInputError (one line) for a bad image."""
    gray, input_size = read_any(image, name, max_long_side)
    gray, scale = working_image(gray, input_size, max_long_side)
    return gray, scale, tuple(input_size)


def working_image(gray: np.ndarray, input_size: tuple[int, int] | None = None,
                  max_long_side: int | None = WORKING_LONG_SIDE) -> tuple[np.ndarray, float]:
    """Resize a grey image to the working resolution.

    ``input_size``: (width, height) of the original input when ``gray`` is already a reduction of it
    (default: ``gray``'s own size).  Returns (working image, scale) with ``scale`` = input pixels per
    working pixel (>= 1; 1 when the input is already small enough).  A reduced decode a little
    below the working size (e.g. 1000 px of a 4000-px JPEG decoded at 1/4) is used as it is.  INTER_AREA (box filter)
    downscaling, so an image upscaled by k and brought back is the original up to rounding.
    """
    h, w = gray.shape[:2]
    in_w, in_h = input_size if input_size is not None else (w, h)
    target = working_size((in_w, in_h), max_long_side)
    if target[0] > w and (in_w, in_h) != (w, h):  # a reduced decode slightly below the working size: keep it
        target = (w, h)
    if (w, h) != target:
        interpolation = cv2.INTER_AREA if target[0] < w else cv2.INTER_LINEAR
        gray = cv2.resize(gray, target, interpolation=interpolation)
    return gray, in_w / target[0]


def encode_png(image: np.ndarray) -> bytes:
    """PNG bytes of an image (cv2.imencode; the caller writes them with Python's own file I/O, which
    handles any file name, where cv2.imwrite crashes on names that are not valid UTF-8)."""
    ok, buffer = cv2.imencode(".png", image)
    if not ok:
        raise _error("could not encode the overlay as PNG")
    return buffer.tobytes()


def focal_and_pp_to_working(focal, principal_point, scale: float, input_size: tuple[int, int],
                            working_size: tuple[int, int]):
    """The user's focal length / principal point (input pixels) in working pixels (one image).

    The focal length divides by ``scale`` (input pixels per working pixel); the principal point
    moves as the resize moves a pixel (:func:`fr_torch.core.geometry.conventions.resize_points`, pixel centres at
    integers), so the input's centre is the working image's centre.  ``input_size``,
    ``working_size``: (width, height) in pixels."""
    focal = None if focal is None else float(focal) / scale
    if principal_point is not None:
        x, y = resize_points(principal_point, input_size, working_size)
        principal_point = (float(x), float(y))
    return focal, principal_point


def result_to_input_pixels(result, scale: float, input_size: tuple[int, int]) -> None:
    """Rescale, in place, a result estimated at the working resolution to the input's pixels.

    The focal length is multiplied by ``scale`` (input pixels per working pixel); points (the
    principal point, the segments' endpoints, the ranked vanishing points) move as the resize
    moves a pixel (:func:`fr_torch.core.geometry.conventions.resize_points`: ``x_in = (x_work + 0.5) w_in / w_work
    - 0.5``, likewise y); angles, rotation, cues and labels are unchanged; width / height become the
    input's; the HFOV and the vanishing points follow from the rescaled camera.
    """
    working = (result.width, result.height)
    if result.width > 0:
        result.width, result.height = int(input_size[0]), int(input_size[1])
    if scale == 1.0 or not result.ok:
        return
    if result.camera is not None:
        result.camera = result.camera.resized(result.width, result.height, factor=scale)
    if result.segments is not None:
        result.segments = resize_points(result.segments, working, input_size)
    if result.ranked_vanishing_points is not None:
        result.ranked_vanishing_points = resize_homogeneous(result.ranked_vanishing_points, working, input_size)
        result.vanishing_point_support = np.asarray(result.vanishing_point_support, np.float64) * scale


def read_any(image, name: str, max_long_side: int | None = WORKING_LONG_SIDE) -> tuple[np.ndarray, tuple[int, int]]:
    """Grey uint8 image and the input's (width, height) from a path (bounded decode, see
    :func:`read_image`) or an array (any format :func:`~fr_torch.images.convert.to_bgr8` accepts)."""

    if isinstance(image, (str, bytes, os.PathLike)):
        # Decoded in colour and converted like an array (not decoded to grey: a JPEG's grey decode
        # differs from BGR -> grey by a level here and there, enough to move some LSD segments), so
        # a path and the array cv2.imread gives for it are calibrated alike (+0.3 ms at 640 x 480).
        image, size = read_image(image, max_long_side)
        return (image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)), size
    gray = to_gray8(image) if not (isinstance(image, np.ndarray) and image.ndim == 2 and image.dtype == np.uint8) \
        else image
    return gray, (gray.shape[1], gray.shape[0])


def load_image(path: str | Path) -> np.ndarray:
    """Read an image file as an 8-bit BGR array (H, W, 3).  Raises FRInputError on any problem.

    Safe on hostile input (regular files only, declared size checked before decoding, bounded
    decode memory, EXIF orientation applied): see :mod:`fr_torch.images.io`.  A huge image (colour
    buffer > ~400 MB) comes back reduced by 2, 4 or 8; use :func:`fr_torch.read_image`
    to get the input's size as well.
    """

    image, _ = read_image(path)
    return to_bgr8(image, str(path))
