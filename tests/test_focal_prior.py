"""The soft focal prior: option parsing, EXIF reading (JPEGs written here), and its effect."""
import json
import math
import struct

import cv2
import numpy as np
import pytest

from fr_torch.errors import FRInputError
from fr_torch.runtime.focal_prior import (
    DIAGONAL_35MM,
    TAG_FOCAL_35MM,
    TAG_FOCAL_LENGTH,
    TAG_PIXEL_X,
    TAG_PIXEL_Y,
    TAG_PLANE_UNIT,
    TAG_PLANE_X_RES,
    FocalPrior,
    exif_focal_px,
    parse_focal_prior,
    read_exif_tags,
)


def _ifd(entries, order, start):
    """IFD bytes at offset ``start`` of the TIFF block: entries (tag, type, value); RATIONALs and
    SRATIONALs are (num, den) stored after the IFD."""
    head = struct.pack(order + "H", len(entries))
    tail = b""
    body = b""
    data_at = start + 2 + 12 * len(entries) + 4
    for tag, kind, value in entries:
        if kind in (5, 10):
            body += struct.pack(order + "HHII", tag, kind, 1, data_at + len(tail))
            tail += struct.pack(order + ("II" if kind == 5 else "ii"), *value)
        elif kind == 3:
            body += struct.pack(order + "HHIHH", tag, kind, 1, value, 0)
        else:
            body += struct.pack(order + "HHII", tag, kind, 1, value)
    return head + body + struct.pack(order + "I", 0) + tail


def exif_app1(exif_entries, orientation=1, big_endian=False) -> bytes:
    """An APP1 segment: IFD0 (Orientation, ExifIFD pointer) and an Exif IFD with ``exif_entries``."""
    order = ">" if big_endian else "<"
    ifd0_entries = [(0x0112, 3, orientation), (0x8769, 4, 0)]
    ifd0_len = len(_ifd(ifd0_entries, order, 8))
    ifd0 = _ifd([(0x0112, 3, orientation), (0x8769, 4, 8 + ifd0_len)], order, 8)
    tiff = (b"MM" if big_endian else b"II") + struct.pack(order + "HI", 42, 8) + ifd0
    tiff += _ifd(exif_entries, order, len(tiff))
    payload = b"Exif\x00\x00" + tiff
    return b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload


def write_jpeg(path, image, app1: bytes | None):
    ok, data = cv2.imencode(".jpg", image)
    assert ok
    data = data.tobytes()
    path.write_bytes(data[:2] + (app1 or b"") + data[2:])
    return path


@pytest.fixture
def grey():
    return np.full((48, 64), 128, np.uint8)


def test_parse_option():
    option = parse_focal_prior("800")
    assert option.prior == FocalPrior(800.0, 10.0, "user") and not option.exif
    assert parse_focal_prior("800,25%").prior.sigma_pct == 25.0
    assert parse_focal_prior("exif").exif and parse_focal_prior("EXIF,5").sigma_pct == 5.0
    for bad in ("", "abc", "0", "-5", "nan", "800,0", "800,x", "800,5,6", "inf"):
        with pytest.raises(FRInputError):
            parse_focal_prior(bad)
    prior = FocalPrior(640.0, 10.0)
    centre, sigma = prior.log_ratio_prior(640, 480)
    assert centre == pytest.approx(0.0) and sigma == pytest.approx(math.log(1.1))
    assert prior.to_json() == {"source": "user", "focal_px": 640.0, "sigma_pct": 10.0}


@pytest.mark.parametrize("big_endian", [False, True])
def test_exif_35mm(tmp_path, grey, big_endian):
    path = write_jpeg(tmp_path / "a.jpg", grey, exif_app1([(TAG_FOCAL_35MM, 3, 28)], big_endian=big_endian))
    focal, how = exif_focal_px(path, 640, 480)
    assert focal == pytest.approx(28 / DIAGONAL_35MM * 800.0) and "35mm" in how
    # a portrait reading of the same photo (EXIF orientation 6): the diagonal, so f, is the same
    assert exif_focal_px(path, 480, 640)[0] == pytest.approx(focal)


def test_exif_focal_plane(tmp_path, grey):
    # 4.25 mm lens, 1000 pixels per mm (1 um pixels), EXIF size 4000 x 3000; the file read at 640 x 480
    entries = [(TAG_FOCAL_LENGTH, 5, (425, 100)), (TAG_PLANE_X_RES, 5, (1000, 1)), (TAG_PLANE_UNIT, 3, 4),
               (TAG_PIXEL_X, 4, 4000), (TAG_PIXEL_Y, 4, 3000)]
    path = write_jpeg(tmp_path / "b.jpg", grey, exif_app1(entries))
    focal, _ = exif_focal_px(path, 640, 480)
    assert focal == pytest.approx(4.25 * 1000 * 640 / 4000)
    # FocalLength alone: the camera's sensor is unknown -> no prior, with the reason
    path = write_jpeg(tmp_path / "c.jpg", grey, exif_app1([(TAG_FOCAL_LENGTH, 5, (425, 100))]))
    focal, why = exif_focal_px(path, 640, 480)
    assert focal is None and "unknown" in why


@pytest.mark.parametrize("entries", [[(TAG_FOCAL_35MM, 3, 0)], [(TAG_FOCAL_35MM, 3, 10000)],
                                     [(TAG_FOCAL_LENGTH, 10, (-5, 1)), (TAG_PLANE_X_RES, 5, (1000, 1)),
                                      (TAG_PLANE_UNIT, 3, 4)],
                                     [(TAG_FOCAL_LENGTH, 5, (10000, 1)), (TAG_PLANE_X_RES, 5, (1000, 1)),
                                      (TAG_PLANE_UNIT, 3, 4)],
                                     [(TAG_FOCAL_LENGTH, 5, (4, 0)), (TAG_PLANE_X_RES, 5, (1000, 1)),
                                      (TAG_PLANE_UNIT, 3, 4)]])
def test_exif_nonsense_gives_no_prior(tmp_path, grey, entries):
    focal, why = exif_focal_px(write_jpeg(tmp_path / "n.jpg", grey, exif_app1(entries)), 640, 480)
    assert focal is None and "believable" in why


def test_exif_missing_or_corrupt(tmp_path, grey):
    assert exif_focal_px(write_jpeg(tmp_path / "plain.jpg", grey, None), 64, 48) == (None, "no EXIF")
    assert exif_focal_px(tmp_path / "absent.jpg", 64, 48)[0] is None
    good = write_jpeg(tmp_path / "g.jpg", grey, exif_app1([(TAG_FOCAL_35MM, 3, 28)])).read_bytes()
    rng = np.random.default_rng(0)
    for trial in range(300):  # flipped bytes and truncations inside the EXIF block: never an exception
        data = bytearray(good)
        for _ in range(3):
            data[rng.integers(4, 120)] = rng.integers(0, 256)
        read_exif_tags(bytes(data[:rng.integers(4, len(data))]))
    assert read_exif_tags(b"") == {} and read_exif_tags(b"\xff\xd8\xff\xe1\x00") == {}


def test_cli_focal_prior(tmp_path, capsys):
    from pathlib import Path

    from fr_torch.cli.main import main

    room = Path(__file__).resolve().parents[1] / "examples" / "room.png"  # rendered with f = 420 px
    image = cv2.imread(str(room))
    true_f = 420.0
    f35 = true_f / 800.0 * DIAGONAL_35MM
    jpeg = write_jpeg(tmp_path / "room.jpg", image, exif_app1([(TAG_FOCAL_35MM, 3, int(round(f35)))]))
    png = tmp_path / "room.png"
    cv2.imwrite(str(png), image)
    code = main(["calibrate", str(jpeg), str(png), "--focal-prior", "exif", "--fast", "--no-reliability",
                 "--workers", "0"])
    out = capsys.readouterr()
    assert code == 0, out.err
    with_exif, without = [json.loads(line) for line in out.out.splitlines()]
    assert with_exif["focal_prior"]["source"] == "exif"
    assert with_exif["focal_prior"]["focal_px"] == pytest.approx(round(f35) / DIAGONAL_35MM * 800.0)
    assert abs(with_exif["focal_px"] / true_f - 1) < 0.05
    assert without["focal_prior"] is None and without["focal_prior_reason"] == "no EXIF"
    assert main(["calibrate", str(png), "--focal-prior", "12,abc"]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    assert main(["calibrate", str(png), "--focal-prior", "500", "--focal", "500"]) == 2
    assert "--focal fixes" in capsys.readouterr().err


def test_prior_pulls_a_single_photo():
    from fr_torch import FREstimator
    from fr_torch.runtime.shared_focal import apply_focal_priors
    from fr_torch.synthetic import random_rotation, synthetic_segments

    segments, _ = synthetic_segments(600.0, random_rotation(np.random.default_rng(3)), seed=3, n_per_family=40)
    estimator = FREstimator(reliability=None)
    alone = estimator.calibrate_segments([segments, segments], [(640, 480)] * 2)
    out = apply_focal_priors(estimator, alone, [None, FocalPrior(600.0 * 1.3, 3.0)])
    assert out[0] is alone[0]  # no prior: untouched
    assert out[1].ok and out[1].focal_px > alone[1].focal_px * 1.1  # a narrow prior far away wins
    loose = apply_focal_priors(estimator, alone, [FocalPrior(600.0, 50.0), None])[0]
    assert abs(loose.focal_px / 600.0 - 1) < 0.03
