"""A soft prior on the focal length: a number the user gives (``--focal-prior PX[,SIGMA%]``) or the
photo's EXIF (``--focal-prior exif[,SIGMA%]``).

The prior is log-normal: ``log p(f) = -(log(f / f_p))^2 / (2 s^2)`` with ``s = log(1 + sigma_pct / 100)``,
added once to the tempered focal log-likelihood of :mod:`fr_torch.runtime.shared_focal` (a photo alone is a
group of one).  ``--focal`` still fixes f exactly.

EXIF (:func:`exif_focal_px`, from the JPEG's APP1 segment, parsed here: no PIL needed), in this order:

* ``FocalLengthIn35mmFilm`` (tag 0xA405, mm): the focal length of a 36 x 24 mm frame with the same
  diagonal field of view, so ``f_px = f35 / 43.267 mm x diagonal_px`` of the image as fR reads it
  (after EXIF orientation; the diagonal does not change with it).
* ``FocalLength`` (0x920A, mm) with the sensor's pixel density ``FocalPlaneXResolution`` (0xA20E)
  in ``FocalPlaneResolutionUnit`` (0xA210: 2 = inch, 3 = cm, 4 = mm, 5 = um): ``f_px = f_mm x
  pixels per mm``, rescaled from the EXIF pixel size (``PixelXDimension`` / ``PixelYDimension``,
  0xA002 / 0xA003, long side) to the image's long side when both are known.

Default width :data:`EXIF_SIGMA_PCT` = 10 %: the 35 mm equivalent is rounded to a whole mm and makers
differ on diagonal vs width equivalence (4 % on a 4:3 photo); video modes, digital zoom and
stabilisation crop further.  A value outside :data:`EXIF_FOV_RANGE_DEG` of FOV across the long side
(0 mm, negative, 10,000 mm ...) gives no prior and a reason; a corrupt EXIF block gives no prior.
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from fr_torch.errors import FRInputError
from fr_torch.images.io import jpeg_segments

#: Default width (1 sigma, percent of f) of a prior read from EXIF.
EXIF_SIGMA_PCT = 10.0
#: Default width of a user prior given without one.
USER_SIGMA_PCT = 10.0
#: FOV across the long side (degrees) an EXIF focal length must give to be believed.
EXIF_FOV_RANGE_DEG = (5.0, 150.0)
DIAGONAL_35MM = math.hypot(36.0, 24.0)  # 43.267 mm
EXIF_READ_BYTES = 1 << 18  # the APP1 segment lies within the first 64 KB after a few markers

TAG_EXIF_IFD = 0x8769
TAG_FOCAL_LENGTH = 0x920A
TAG_FOCAL_35MM = 0xA405
TAG_PIXEL_X = 0xA002
TAG_PIXEL_Y = 0xA003
TAG_PLANE_X_RES = 0xA20E
TAG_PLANE_UNIT = 0xA210
PLANE_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}  # unit code -> millimetres per unit


@dataclass(frozen=True)
class FocalPrior:
    """A log-normal prior on one photo's focal length.

    ``focal_px``: its centre, pixels of the image as fR reads it (after EXIF orientation);
    ``sigma_pct``: its width, 1 sigma in percent of f (> 0); ``source``: ``"user"`` or ``"exif"``;
    ``detail``: how it was obtained (e.g. the EXIF tag and its value).
    """

    focal_px: float
    sigma_pct: float
    source: str = "user"
    detail: str = ""

    def __post_init__(self):
        if not (math.isfinite(self.focal_px) and self.focal_px > 0):
            raise FRInputError(f"focal prior: the focal length must be a finite number > 0 px, got {self.focal_px!r}")
        if not (math.isfinite(self.sigma_pct) and 0 < self.sigma_pct <= 1000):
            raise FRInputError(f"focal prior: sigma must be in (0, 1000] %, got {self.sigma_pct!r}")

    def log_ratio_prior(self, width: int, height: int) -> tuple[float, float]:
        """``(log(f_p / L), s)`` for an image of ``width`` x ``height`` (L = long side), s in log f."""
        return math.log(self.focal_px / max(width, height)), math.log1p(self.sigma_pct / 100.0)

    def to_json(self) -> dict:
        """``{source, focal_px, sigma_pct}`` (the ``focal_prior`` field of the CLI's JSON)."""
        return {"source": self.source, "focal_px": float(self.focal_px), "sigma_pct": float(self.sigma_pct)}


@dataclass(frozen=True)
class FocalPriorOption:
    """The parsed ``--focal-prior`` option: a fixed prior for every photo (``prior``) or one read
    from each photo's EXIF (``exif`` True, width ``sigma_pct``)."""

    prior: FocalPrior | None = None
    exif: bool = False
    sigma_pct: float = EXIF_SIGMA_PCT

    def for_image(self, path, width: int, height: int) -> tuple[FocalPrior | None, str]:
        """(prior or None, reason when None) for the photo at ``path`` read as ``width`` x ``height``."""
        if not self.exif:
            return self.prior, ""
        if not isinstance(path, (str, Path)):
            return None, "no EXIF (not a file)"
        focal, detail = exif_focal_px(path, width, height)
        if focal is None:
            return None, detail
        return FocalPrior(focal, self.sigma_pct, "exif", detail), ""


def image_priors(option: FocalPriorOption | None, paths: Sequence, results: Sequence) -> tuple[list, list[str]]:
    """(one prior or None per result, one reason per result: why it has none, "" otherwise) for the
    photos ``paths`` (file paths, or arrays: no EXIF) and their per-photo ``results`` under the
    parsed ``--focal-prior`` ``option`` (None: no prior for any); a failed result (no size) gets none."""
    priors, reasons = [], []
    for path, result in zip(paths, results):
        if option is None or result.width <= 0:
            priors.append(None)
            reasons.append("")
            continue
        prior, reason = option.for_image(path, result.width, result.height)
        priors.append(prior)
        reasons.append(reason)
    return priors, reasons


def group_prior(priors: Sequence):
    """The prior of a group of one camera's photos (added once to its combination): the first photo's
    that has one (photos of one camera read alike), None when none has."""
    return next((p for p in priors if p is not None), None)


def parse_focal_prior(text: str) -> FocalPriorOption:
    """``PX[,SIGMA%]`` or ``exif[,SIGMA%]`` -> :class:`FocalPriorOption`; FRInputError (one line) otherwise."""
    parts = [p.strip() for p in str(text).split(",")]
    usage = f"--focal-prior expects PX[,SIGMA%] or exif[,SIGMA%], got {text!r}"
    if not 1 <= len(parts) <= 2 or not parts[0]:
        raise FRInputError(usage)
    sigma = None
    if len(parts) == 2:
        try:
            sigma = float(parts[1].rstrip("%"))
        except ValueError:
            raise FRInputError(usage) from None
        if not (math.isfinite(sigma) and 0 < sigma <= 1000):
            raise FRInputError(f"--focal-prior: SIGMA must be a percentage in (0, 1000], got {parts[1]!r}")
    if parts[0].lower() == "exif":
        return FocalPriorOption(exif=True, sigma_pct=EXIF_SIGMA_PCT if sigma is None else sigma)
    try:
        focal = float(parts[0])
    except ValueError:
        raise FRInputError(usage) from None
    if not (math.isfinite(focal) and focal > 0):
        raise FRInputError(f"--focal-prior: PX must be a focal length > 0 in pixels, got {parts[0]!r}")
    return FocalPriorOption(prior=FocalPrior(focal, USER_SIGMA_PCT if sigma is None else sigma, "user"))


# ---------------------------------------------------------------------------------------- EXIF


def jpeg_exif_block(data: bytes) -> bytes | None:
    """The TIFF structure of a JPEG's EXIF APP1 segment (from the byte order mark on), or None."""
    if data[:2] != b"\xff\xd8":
        return None
    for marker, length, body in jpeg_segments(data):
        if length < 2:
            return None
        if marker == 0xE1 and body[:6] == b"Exif\x00\x00":
            return body[6:]
    return None


_TYPE_SIZES = {1: 1, 2: 1, 3: 2, 4: 4, 5: 8, 7: 1, 9: 4, 10: 8}


def _read_ifd(tiff: bytes, offset: int, order: str) -> dict[int, float | int]:
    """Numeric tags of the IFD at ``offset``: tag -> first value (SHORT, LONG, RATIONAL and signed
    kinds; a RATIONAL as a float, nan for a zero denominator).  Bounds-checked: bad offsets are skipped."""
    values: dict[int, float | int] = {}
    if offset < 8 or offset + 2 > len(tiff):
        return values
    count = struct.unpack(order + "H", tiff[offset:offset + 2])[0]
    for k in range(min(count, 512)):
        entry = offset + 2 + 12 * k
        if entry + 12 > len(tiff):
            break
        tag, kind, n = struct.unpack(order + "HHI", tiff[entry:entry + 8])
        size = _TYPE_SIZES.get(kind)
        if size is None or n < 1:
            continue
        if size * n <= 4:
            where = entry + 8
        else:
            where = struct.unpack(order + "I", tiff[entry + 8:entry + 12])[0]
            if where + size > len(tiff):
                continue
        raw = tiff[where:where + size]
        if kind == 3:
            values[tag] = struct.unpack(order + "H", raw)[0]
        elif kind == 4:
            values[tag] = struct.unpack(order + "I", raw)[0]
        elif kind == 9:
            values[tag] = struct.unpack(order + "i", raw)[0]
        elif kind in (5, 10):
            num, den = struct.unpack(order + ("II" if kind == 5 else "ii"), raw)
            values[tag] = num / den if den else math.nan
        elif kind in (1, 7):
            values[tag] = raw[0]
    return values


def read_exif_tags(data: bytes) -> dict[int, float | int]:
    """Numeric tags of IFD0 and the Exif IFD of a JPEG file's bytes; {} without (readable) EXIF."""
    try:
        tiff = jpeg_exif_block(data)
        if tiff is None or len(tiff) < 8 or tiff[:2] not in (b"II", b"MM"):
            return {}
        order = "<" if tiff[:2] == b"II" else ">"
        if struct.unpack(order + "H", tiff[2:4])[0] != 42:
            return {}
        tags = _read_ifd(tiff, struct.unpack(order + "I", tiff[4:8])[0], order)
        exif_offset = tags.get(TAG_EXIF_IFD)
        if isinstance(exif_offset, int):
            tags.update(_read_ifd(tiff, exif_offset, order))
        return tags
    except (struct.error, IndexError, ValueError, OverflowError):
        return {}


def focal_from_tags(tags: dict, width: int, height: int) -> tuple[float | None, str]:
    """(focal length in pixels of a ``width`` x ``height`` image, how) from EXIF tags, or (None, why)."""
    long_side = max(width, height)
    low, high = EXIF_FOV_RANGE_DEG
    f_min = 0.5 * long_side / math.tan(math.radians(high) / 2)
    f_max = 0.5 * long_side / math.tan(math.radians(low) / 2)

    def believable(focal: float) -> bool:
        return math.isfinite(focal) and f_min <= focal <= f_max

    reasons = []
    f35 = tags.get(TAG_FOCAL_35MM)
    if f35 is not None:
        focal = float(f35) / DIAGONAL_35MM * math.hypot(width, height)
        if believable(focal):
            return focal, f"FocalLengthIn35mmFilm {float(f35):g} mm"
        reasons.append(f"FocalLengthIn35mmFilm {float(f35):g} mm is not a believable focal length")
    f_mm, resolution, unit = tags.get(TAG_FOCAL_LENGTH), tags.get(TAG_PLANE_X_RES), tags.get(TAG_PLANE_UNIT, 2)
    if f_mm is not None and resolution is not None and unit in PLANE_UNIT_MM:
        focal = float(f_mm) * float(resolution) / PLANE_UNIT_MM[unit]
        exif_long = max(float(tags.get(TAG_PIXEL_X, 0) or 0), float(tags.get(TAG_PIXEL_Y, 0) or 0))
        if exif_long > 0:
            focal *= long_side / exif_long
        if believable(focal):
            return focal, f"FocalLength {float(f_mm):g} mm x FocalPlaneXResolution"
        reasons.append(f"FocalLength {float(f_mm):g} mm with the focal plane resolution is not a believable focal "
                       "length")
    elif f_mm is not None:
        reasons.append("FocalLength without FocalLengthIn35mmFilm or the sensor's resolution (camera unknown)")
    if not reasons:
        return None, "no focal length in EXIF"
    return None, "; ".join(reasons)


def exif_focal_px(path, width: int, height: int) -> tuple[float | None, str]:
    """(focal length in pixels, how) from the EXIF of the JPEG at ``path`` read as ``width`` x ``height``
    pixels (after EXIF orientation), or (None, why).  Never raises for a bad or missing file."""
    try:
        with open(path, "rb") as handle:
            data = handle.read(EXIF_READ_BYTES)
    except OSError as exc:
        return None, f"EXIF not readable ({exc.strerror or exc})"
    tags = read_exif_tags(data)
    if not tags:
        return None, "no EXIF"
    return focal_from_tags(tags, width, height)
