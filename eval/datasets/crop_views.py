"""Narrower cameras from real photos: crops of a calibrated dataset centred on its principal point.

    python -m fr_eval.datasets.crop_views --dataset yud --size 400x300 --out data_local/yud-crop-400x300
    fr eval --dataset panoviews --data-root data_local/yud-crop-400x300 --split test ...

A crop of a photo is the photo a camera with the same focal length (pixels) and orientation but a
smaller sensor would have taken: the field of view narrows (YUD's 674.9 px over 400 px: 33.0°
instead of 50.7° over 640 px) while the scene, the lines and the ground truth stay real.  Each
crop is centred on the image's *calibrated* principal point, rounded to whole pixels, so the
crop's centre (:func:`fr_torch.core.geometry.conventions.image_centre`) -- the principal point every method
assumes -- is the true one to within half a pixel (YUD: 0.05 px in x and y; the full YUD frames,
evaluated with the image centre as in the paper, are 17 px off).

Writes the ``fr make-dataset`` layout (:mod:`fr_eval.datasets.make_dataset`), which the ``panoviews``
loader reads: ``images/<name>.png`` (lossless), ``gt.csv`` (one row per image, same columns:
the crop's centre as principal point, focal, the crop's FOV, pan / tilt / roll / pitch, R
world->camera, ``group`` = image name, the dataset's own train / test split), ``dataset.json``
(command, source, offsets).  Images too small for the crop, or without a known focal length and
rotation, are skipped and listed there.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import torch

from fr_eval.datasets.make_dataset import parse_range, view_distortions
from fr_eval.datasets.panoviews import GT_COLUMNS, R_COLUMNS
from fr_eval.datasets.registry import load_dataset
from fr_torch.core.geometry.conventions import hfov_from_focal, image_centre, pan_from_rotation
from fr_torch.images.io import load_image
from fr_torch.images.lens import distort_image


def _size(text: str) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        width = height = 0
    if width < 16 or height < 16:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT of at least 16x16 pixels, got {text!r}")
    return width, height


def crop_origin(principal_point: tuple[float, float], size: tuple[int, int]) -> tuple[int, int]:
    """Top-left pixel (x0, y0) of the ``size`` = (width, height) crop whose centre
    (:func:`fr_torch.core.geometry.conventions.image_centre`, ``((w - 1) / 2, (h - 1) / 2)`` in the crop) lies
    nearest to ``principal_point`` (pixels)."""
    cx, cy = image_centre(*size)
    return int(round(principal_point[0] - cx)), int(round(principal_point[1] - cy))


def crop_dataset(samples, size: tuple[int, int], out: Path, distortion_k=None) -> dict:
    """Write the crops of ``samples`` (harness records with a camera) to ``out``; returns the
    summary written to ``dataset.json`` (without the command).

    ``distortion_k``: None, or a callable name -> k: each crop is then the photo the same camera
    would take through a division-model lens of that k (:func:`fr_torch.images.lens.distort_image`,
    centre = the crop's centre; barrel pulls in pixels from beyond the crop, borders replicated),
    and ``gt.csv`` gains the column ``k``."""
    width, height = size
    cx, cy = image_centre(width, height)  # the crops' principal point (gt.csv cx, cy)
    (out / "images").mkdir(parents=True, exist_ok=True)
    rows, skipped, offsets = [], [], []
    for sample in samples:
        camera = sample.camera
        if camera is None or camera.focal_px is None or camera.rotation is None:
            skipped.append(f"{sample.name}: no focal length and rotation")
            continue
        x0, y0 = crop_origin(camera.principal_point, size)
        if x0 < 0 or y0 < 0 or x0 + width > sample.width or y0 + height > sample.height:
            skipped.append(f"{sample.name}: a {width}x{height} crop around the principal point leaves the "
                           f"{sample.width}x{sample.height} image")
            continue
        k = None if distortion_k is None else float(distortion_k(sample.name))
        if k is None:
            image = load_image(sample.image_path)[y0:y0 + height, x0:x0 + width]
        else:
            image = distort_image(load_image(sample.image_path), k, size, source_centre=(x0 + cx, y0 + cy))
        file = f"images/{sample.name}.png"
        cv2.imwrite(str(out / file), image)
        rotation = np.asarray(camera.rotation, dtype=np.float64)
        offsets.append((camera.principal_point[0] - x0 - cx, camera.principal_point[1] - y0 - cy))
        row = {"file": file, "pano": sample.name, "group": sample.name, "split": sample.split or "all",
               "width": width, "height": height, "cx": cx, "cy": cy, "focal_px": float(camera.focal_px),
               "hfov_deg": hfov_from_focal(float(camera.focal_px), width),
               "pan_deg": float(pan_from_rotation(torch.as_tensor(rotation))),
               "tilt_deg": float(sample.tilt_deg), "roll_deg": float(sample.roll_deg),
               "pitch_deg": float(sample.pitch_deg), "manhattan_known": True, "manhattan_yaw_deg": 0.0}
        row.update({c: float(v) for c, v in zip(R_COLUMNS, rotation.reshape(-1).tolist())})
        if k is not None:
            row["k"] = k
        rows.append(row)
    columns = GT_COLUMNS + ([] if distortion_k is None else ["k"])
    pd.DataFrame(rows, columns=columns).to_csv(out / "gt.csv", index=False, float_format="%.10g")
    offsets = np.abs(np.asarray(offsets)) if offsets else np.zeros((0, 2))
    return {"generator": "fr_eval.datasets.crop_views", "size": [width, height], "images": len(rows),
            "skipped": skipped,
            "principal_point": "the crop centre ((w-1)/2, (h-1)/2) (gt.csv cx, cy); the true principal point is off "
                               "by at most "
                               f"{offsets.max(initial=0.0):.2f} px (crops are whole pixels)",
            "rotation": "world->camera of the source image (a crop does not rotate the camera)",
            "splits": {s: int(sum(r["split"] == s for r in rows)) for s in ("train", "test")}}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", default="yud", help="a registered dataset with focal lengths and rotations")
    parser.add_argument("--split", default="all")
    parser.add_argument("--size", type=_size, required=True, help="crop WIDTHxHEIGHT in pixels, e.g. 400x300")
    parser.add_argument("--data-root", default=None)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--k-range", type=parse_range, default=None, metavar="MIN:MAX",
                        help="warp each crop through a division-model lens, k ~ U[MIN, MAX] per image (normalised "
                             "by half the diagonal; seeded by --seed and the image name)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    samples = load_dataset(args.dataset, root=args.data_root, split=args.split)
    distortion = None
    if args.k_range:
        distortion = lambda name: view_distortions(args.seed, name, 1, args.k_range)[0]  # noqa: E731
    summary = crop_dataset(samples, args.size, args.out, distortion)
    if args.k_range:
        summary["distortion"] = {"model": "division (fr_torch.core.geometry.lens), centre = the crop centre",
                                 "k_range": list(args.k_range), "seed": args.seed}
    command = " ".join(argv if argv is not None else sys.argv[1:])
    summary = {"command": f"python -m fr_eval.datasets.crop_views {command}", "source": args.dataset, **summary}
    (args.out / "dataset.json").write_text(json.dumps(summary, indent=2))
    print(f"wrote {summary['images']} crops ({args.size[0]}x{args.size[1]}) to {args.out}"
          + (f"; skipped {len(summary['skipped'])}" if summary["skipped"] else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
