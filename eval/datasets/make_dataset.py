"""``fr make-dataset``: PanoContext-fR style planar views cut from equirectangular panoramas.

The paper's PanoContext-fR benchmark consists of 640x480 pinhole views cut from indoor panoramas
with exactly known focal length, tilt and roll.  This command reproduces the recipe for any folder
of upright (gravity-aligned) equirectangular panoramas (or 6-face cube maps, one folder each):

* per panorama ``--views-per-pano`` views (default 15): with ``--fovs 60,75,90,105,120`` (default)
  an equal number of views per horizontal FOV (3 x 5 = 15), or ``--uniform-fov 60:120``;
* per view pan ~ U[-180, 180], pitch ~ U[-30, 30], roll ~ U[-10, 10] degrees, with
  ``R.T = Ry(pan) Rx(pitch) Rz(roll)`` (:func:`fr_torch.core.geometry.conventions.rotation_from_angles`).  The paper's
  "tilt ~ U[-30, 30]" is applied to the **pitch** (elevation of the optical axis); the
  ground truth stores both the paper's horizon tilt (``tan tilt = tan pitch / cos roll``) and the
  pitch, both computed with :func:`fr_torch.core.geometry.conventions.horizon_angles` from the final R, exactly as
  the estimator defines them;
* rendering: :mod:`fr_eval.datasets.panorama` (tensor ``grid_sample``, principal point exactly the image
  centre ``((w - 1) / 2, (h - 1) / 2)``, :func:`fr_torch.core.geometry.conventions.image_centre`).

Outputs in ``--out``: ``images/<pano>_vNN.jpg``, ``gt.csv`` (one row per view: file, pano, group,
split, width, height, cx, cy (the principal point), focal_px, hfov_deg, pan_deg, tilt_deg,
roll_deg, pitch_deg, r00..r22 (the world->camera R, row-major), manhattan_known,
manhattan_yaw_deg), ``dataset.json`` (the parameters), ``contact_sheet.png`` (sample views with
FOV / tilt / roll captions) and, with ``--check-yaw``, ``yaw_check.csv``.

Rotation frame: when the room's Manhattan yaw is known (``--yaw-csv``, or ``--aligned`` for
panoramas whose Manhattan axes are the panorama axes) R is expressed in the room's Manhattan frame
(``manhattan_known = True``; pan is then measured from a Manhattan axis), otherwise in the
panorama frame (only gravity -- tilt, roll, pitch, focal -- is ground truth; column 0/2 of R are
not vanishing directions).  ``--yaw-csv`` accepts either ``pano,manhattan_yaw_deg[,manhattan]
[,group]`` or ZInD's ``manhattan_yaw_derived.csv`` (see :func:`read_yaw_csv`).

Split: **by panorama group**, never by view: groups (by default the ZInD ``partial_room``, so two
panoramas of the same room never straddle the split; ``--group-by pano`` for single panoramas) are
shuffled with ``--seed`` and added to ``test`` greedily while that brings the number of test
*panoramas* closer to ``test_fraction * n_panoramas`` (:func:`split_groups`).  View
angles use a generator seeded with (seed, crc32(pano name)), so a panorama's views do not depend on
which other panoramas are in the folder.

ZInD-fR (the build this project reports; 28 Manhattan panoramas of the ZInD sample tour)::

    fr make-dataset --panoramas ../shared/data/zind_sample_tour/panos \\
        --yaw-csv ../shared/data/zind_sample_tour/manhattan_yaw_derived.csv \\
        --out data_local/zind-fr --seed 0 --views-per-pano 15 --fovs 60,75,90,105,120 \\
        --test-fraction 0.5 --check-yaw

(equivalently ``python -m fr_eval.datasets.make_dataset ...``).  The 4 panoramas of ZInD ``partial_room_09``
(walls at 32-45 deg to the grid) are excluded (``--non-manhattan exclude``, the default).
The split is by room, so no room has views in both halves; ``--check-yaw`` re-measures each
annotated Manhattan yaw with LSD and writes the differences to ``yaw_check.csv`` in the output
folder.  What the published ZInD-fR set holds (panoramas, rooms, views per split and FOV) is
recorded with its tables in ``results/zind-fr/``.

The HorizonNet/PanoContext demo (already Manhattan-aligned) is built with ``--aligned``, e.g.
``--panoramas <dir holding demo_aligned_rgb.png> --aligned --group-by pano``.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
import zlib
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from fr_eval.datasets.panorama import (
    cubemap_to_equirect,
    load_cubemap,
    load_panorama,
    render_views,
    save_rgb,
    yaw_rotation,
)
from fr_eval.datasets.panoviews import GT_COLUMNS, R_COLUMNS
from fr_torch.cli.options import add_device_arguments
from fr_torch.core.geometry.conventions import (
    focal_from_hfov,
    horizon_angles,
    image_centre,
    intrinsics,
    rotation_from_angles,
)

IMAGE_EXTS = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp")
ZIND_WIDTH = 2048  # the width at which ZInD's u_px_of_one_manhattan_axis is given


# --------------------------------------------------------------------------- yaw / panoramas

def zind_yaw_from_u(u_px: float, width: int = ZIND_WIDTH) -> float:
    """Longitude (deg, our pano frame) of ZInD pano column u: ZInD's ``u = (theta+pi)/(2pi)*(W-1)``.

    ZInD's azimuth theta = 0 is the centre column and grows with u (to the right), like our
    longitude, so yaw = u / (W - 1) * 360 - 180.  (Verified with LSD: ``--check-yaw``.)
    """
    return float(u_px) / (width - 1) * 360.0 - 180.0


def read_yaw_csv(path: str | Path, manhattan_min_fraction: float = 0.999,
                 manhattan_max_deviation_deg: float = 2.0) -> pd.DataFrame:
    """Per-panorama Manhattan yaw table indexed by panorama stem.

    Columns of the result: ``manhattan_yaw_deg`` (longitude of one horizontal Manhattan axis in
    the pano frame, degrees), ``manhattan`` (bool: a pure Manhattan room), ``group`` (split group).
    Accepts a generic CSV (``pano``, ``manhattan_yaw_deg``, optional ``manhattan``, ``group``) or
    ZInD's ``manhattan_yaw_derived.csv``: yaw from ``u_px_of_one_manhattan_axis_at_width2048``;
    Manhattan iff ``wall_length_fraction_manhattan >= 0.999`` and
    ``max_wall_deviation_deg <= 2``; group = ``partial_room`` (ZInD's complete_room_06 is a whole
    open-plan floor with 13 panoramas, too coarse for a balanced split).
    """
    df = pd.read_csv(path)
    if "u_px_of_one_manhattan_axis_at_width2048" in df.columns:  # ZInD derived table
        out = pd.DataFrame({
            "pano": [Path(p).stem for p in df["image_path"]],
            "manhattan_yaw_deg": [zind_yaw_from_u(u) for u in df["u_px_of_one_manhattan_axis_at_width2048"]],
            "manhattan": (df["wall_length_fraction_manhattan"] >= manhattan_min_fraction)
            & (df["max_wall_deviation_deg"] <= manhattan_max_deviation_deg),
            "group": df["partial_room"].astype(str),
        })
    else:
        if not {"pano", "manhattan_yaw_deg"} <= set(df.columns):
            raise ValueError(f"{path}: need columns pano, manhattan_yaw_deg (or a ZInD manhattan_yaw_derived.csv)")
        out = pd.DataFrame({"pano": [Path(str(p)).stem for p in df["pano"]],
                            "manhattan_yaw_deg": df["manhattan_yaw_deg"].astype(float)})
        out["manhattan"] = df["manhattan"].astype(bool) if "manhattan" in df.columns else True
        out["group"] = df["group"].astype(str) if "group" in df.columns else out["pano"]
    return out.set_index("pano")


def find_panoramas(folder: Path) -> list[tuple[str, Path]]:
    """(name, path) of equirect images in ``folder`` and of cube-map sub-folders (6 ``*skybox{k}*``)."""
    items = []
    for p in sorted(folder.iterdir()):
        if p.is_file() and p.suffix.lower() in IMAGE_EXTS:
            items.append((p.stem, p))
        elif p.is_dir() and all(any(p.glob(f"*skybox{k}*")) for k in range(6)):
            items.append((p.name, p))
    if not items and all(any(folder.glob(f"*skybox{k}*")) for k in range(6)):
        items.append((folder.name, folder))  # the folder itself is one cube map
    return items


def load_any_panorama(path: Path, device) -> np.ndarray:
    """Equirect (H, W, 3) uint8 RGB from an image file or a cube-map folder."""
    if path.is_dir():
        return cubemap_to_equirect(load_cubemap(path), device=device)
    return load_panorama(path)


# --------------------------------------------------------------------------- sampling / split

def pano_rng(seed: int, name: str) -> np.random.Generator:
    return np.random.default_rng([int(seed), zlib.crc32(name.encode())])


def sample_views(rng: np.random.Generator, n: int, fovs: list[float] | None, uniform_fov,
                 pan=(-180.0, 180.0), pitch=(-30.0, 30.0), roll=(-10.0, 10.0)) -> dict[str, np.ndarray]:
    """Per-view hfov / pan / pitch / roll (degrees) for one panorama."""
    if fovs:
        if n % len(fovs):
            raise ValueError(f"--views-per-pano {n} is not a multiple of the {len(fovs)} FOVs")
        hfov = np.repeat(np.asarray(fovs, dtype=np.float64), n // len(fovs))
    else:
        hfov = rng.uniform(uniform_fov[0], uniform_fov[1], n)
    return {"hfov_deg": hfov, "pan_deg": rng.uniform(*pan, n), "pitch_deg": rng.uniform(*pitch, n),
            "roll_deg": rng.uniform(*roll, n)}


def view_distortions(seed: int, name: str, count: int, k_range: tuple[float, float]) -> np.ndarray:
    """k ~ U[k_range] for the ``count`` views of panorama ``name``, from a generator of its own
    (seeded with (seed, crc32(name), 46)), so the views' angles and FOVs stay those drawn without it."""
    return np.random.default_rng([int(seed), zlib.crc32(name.encode()), 46]).uniform(*k_range, count)


def split_groups(groups: list[str], test_fraction: float, seed: int) -> dict[str, str]:
    """group -> 'train' / 'test' for a list with one group entry per panorama.

    Groups are shuffled with ``seed`` (from their sorted order, so the result does not depend on
    input order) and added greedily to ``test`` whenever that brings the number of *panoramas* in
    test closer to ``test_fraction * n_panoramas``; the rest is ``train``.  With one panorama per
    group this is an exact panorama-level split.
    """
    unique = sorted(set(groups))
    sizes = {g: groups.count(g) for g in unique}
    order = np.random.default_rng(seed).permutation(len(unique))
    target = test_fraction * len(groups)
    n_test, out = 0, {}
    for i in order:
        g = unique[i]
        if abs(n_test + sizes[g] - target) < abs(n_test - target):
            out[g] = "test"
            n_test += sizes[g]
        else:
            out[g] = "train"
    return out


# --------------------------------------------------------------------------- yaw check (LSD)

def yaw_check(pano: np.ndarray, yaw_deg: float, search_deg: float = 45.0, step_deg: float = 0.1,
              hfov_deg: float = 90.0, size=(640, 480), inlier_deg: float = 1.5, device=None) -> dict:
    """Measure the room's Manhattan yaw from LSD segments in level views; compare with ``yaw_deg``.

    Renders 8 level views (pan 0, 45, ..., 315 in the room frame built from ``yaw_deg``), detects
    LSD segments (:func:`fr_torch.detectors.registry.detect_segments`) and, for each yaw offset ``delta`` in
    [-search, search), counts the total length of segments whose direction points (within
    ``inlier_deg``) at one of the two horizontal vanishing points ``K R(delta) e_x``, ``K R(delta)
    e_z``.  Returns the best offset (0 = the given yaw is right; it is only defined modulo 90) and
    the inlier length ratio best / at-0.
    """
    from fr_torch.detectors.registry import detect_segments

    w, h = size
    f = focal_from_hfov(hfov_deg, w)
    pans = torch.arange(0.0, 360.0, 45.0, dtype=torch.float64)
    R = rotation_from_angles(pans, torch.zeros_like(pans), torch.zeros_like(pans))
    views = render_views(pano, R, f, size=size, manhattan_yaw_deg=yaw_deg, device=device)
    segs = []
    for k in range(len(pans)):
        s = detect_segments(views[k])
        segs.append((k, s))
    K = intrinsics(torch.tensor(float(f), dtype=torch.float64), torch.tensor(image_centre(w, h), dtype=torch.float64))
    cos_thr = math.cos(math.radians(inlier_deg))
    segs = [(k, torch.as_tensor(s, dtype=torch.float64)) for k, s in segs if len(s)]
    # coarse scan over the whole 90-deg period, then a fine scan around the best coarse offset
    coarse = torch.arange(-search_deg, search_deg, 0.5, dtype=torch.float64)
    c_best = float(coarse[int(_yaw_scores(segs, R, K, coarse, cos_thr).argmax())])
    fine = torch.cat([torch.arange(c_best - 1.0, c_best + 1.0 + 1e-9, step_deg, dtype=torch.float64),
                      torch.zeros(1, dtype=torch.float64)])
    score = _yaw_scores(segs, R, K, fine, cos_thr)
    i_best = int(score[:-1].argmax())
    best = (float(fine[i_best]) + search_deg) % (2 * search_deg) - search_deg
    return {"best_offset_deg": round(best, 3), "inlier_len_best": float(score[i_best]),
            "inlier_len_at_0": float(score[-1]),
            "ratio_best_over_0": float(score[i_best] / max(float(score[-1]), 1e-9))}


def _yaw_scores(segs, R, K, deltas, cos_thr) -> torch.Tensor:
    """Inlier segment length for each candidate yaw offset (see :func:`yaw_check`)."""
    score = torch.zeros_like(deltas)
    for k, s in segs:
        p1 = torch.cat([s[:, :2], torch.ones(len(s), 1, dtype=torch.float64)], 1)
        p2 = torch.cat([s[:, 2:], torch.ones(len(s), 1, dtype=torch.float64)], 1)
        length = (s[:, 2:] - s[:, :2]).norm(dim=1)
        seg_dir = (s[:, 2:] - s[:, :2]) / length[:, None].clamp_min(1e-9)
        mid = (p1 + p2) / 2
        # the candidate room frame: true frame rotated by delta about the vertical
        Rk = R[k] @ yaw_rotation(deltas)  # (D, 3, 3): X_cam = R_k Ry(delta) X_room'
        best = torch.zeros(len(deltas), len(s), dtype=torch.float64)
        for axis in (0, 2):
            vp = (K @ Rk[:, :, axis:axis + 1])[..., 0]  # (D, 3) homogeneous
            # direction from the midpoint towards the VP (works for finite and infinite VPs)
            to_vp = vp[:, None, :2] - mid[None, :, :2] * vp[:, None, 2:3]  # (D, N, 2)
            to_vp = to_vp / to_vp.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            cos = (to_vp * seg_dir[None]).sum(-1).abs()
            best = torch.maximum(best, cos)
        score += ((best >= cos_thr).double() * length[None]).sum(1)
    return score


# --------------------------------------------------------------------------- contact sheet

def contact_sheet(images: list[np.ndarray], captions: list[str], path: Path, cols: int = 5,
                  thumb_w: int = 256) -> None:
    """Write a grid of thumbnails with captions (matplotlib, Agg)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(images)
    if n == 0:
        return
    cols = min(cols, n)
    rows = math.ceil(n / cols)
    h, w = images[0].shape[:2]
    fig, axes = plt.subplots(rows, cols, figsize=(cols * 3.2, rows * 3.2 * h / w + rows * 0.35), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, img, cap in zip(axes.ravel(), images, captions):
        ax.imshow(img)
        ax.set_title(cap, fontsize=7)
        # mark the principal point (imshow puts pixel centres at integers, as fR does)
        cx, cy = image_centre(img.shape[1], img.shape[0])
        ax.plot([cx], [cy], "+", color="yellow", ms=6)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


# --------------------------------------------------------------------------- CLI

def _parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 640x480, got {text!r}") from None
    return w, h


def _parse_fovs(text: str) -> list[float]:
    return [float(x) for x in text.split(",") if x.strip()]


def parse_range(text: str) -> tuple[float, float]:
    """``"MIN:MAX"`` -> (MIN, MAX) floats (an argparse type)."""
    a, b = (float(x) for x in text.split(":"))
    return a, b


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``fr make-dataset``."""
    parser.add_argument("--panoramas", required=True, type=Path,
                        help="folder of upright equirect panoramas (and/or cube-map sub-folders)")
    parser.add_argument("--out", required=True, type=Path, help="output folder (created)")
    parser.add_argument("--views-per-pano", type=int, default=15)
    fov = parser.add_mutually_exclusive_group()
    fov.add_argument("--fovs", type=_parse_fovs, default=None,
                     help="comma-separated horizontal FOVs (deg), equal number of views each (default 60,75,90,105,120)")
    fov.add_argument("--uniform-fov", type=parse_range, default=None, metavar="MIN:MAX",
                     help="horizontal FOV ~ U[MIN, MAX] degrees instead of fixed FOVs")
    parser.add_argument("--size", type=_parse_size, default=(640, 480), help="view size WxH (default 640x480)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--yaw-csv", type=Path, default=None,
                        help="per-panorama Manhattan yaw (generic pano,manhattan_yaw_deg CSV or ZInD manhattan_yaw_derived.csv)")
    parser.add_argument("--aligned", action="store_true",
                        help="panoramas are Manhattan-aligned (yaw 0) when not in --yaw-csv")
    parser.add_argument("--non-manhattan", choices=("exclude", "keep"), default="exclude",
                        help="panoramas flagged non-Manhattan in --yaw-csv: drop them (default) or keep with manhattan_known=False")
    parser.add_argument("--group-by", choices=("room", "pano"), default="room",
                        help="split unit: the yaw CSV's room group (ZInD partial_room; default; falls back to the panorama) or the panorama")
    parser.add_argument("--test-fraction", type=float, default=0.5)
    parser.add_argument("--pitch-range", type=parse_range, default=(-30.0, 30.0), metavar="MIN:MAX")
    parser.add_argument("--roll-range", type=parse_range, default=(-10.0, 10.0), metavar="MIN:MAX")
    parser.add_argument("--interp", choices=("bilinear", "bicubic"), default="bilinear")
    parser.add_argument("--k-range", type=parse_range, default=None, metavar="MIN:MAX",
                        help="render through a division-model lens, k ~ U[MIN, MAX] per view (normalised by half "
                             "the diagonal; fr_torch.core.geometry.lens), e.g. -0.4:0 for ZInD-fR-D; the views' angles "
                             "and FOVs are those of the same seed without it; gt.csv gains a column k")
    parser.add_argument("--format", choices=("jpg", "png"), default="jpg", help="view image format (jpg = quality 95)")
    add_device_arguments(parser)
    parser.add_argument("--check-yaw", action="store_true",
                        help="measure each Manhattan pano's yaw with LSD and write yaw_check.csv")
    parser.add_argument("--sheet-views", type=int, default=15, help="views on the contact sheet")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    """Generate the dataset; returns a process exit code."""
    from tqdm import tqdm

    t0 = time.time()
    fovs = args.fovs if args.fovs is not None or args.uniform_fov is not None else [60.0, 75.0, 90.0, 105.0, 120.0]
    if args.uniform_fov is not None:
        fovs = None
    if not args.panoramas.is_dir():
        print(f"error: {args.panoramas} is not a folder", file=sys.stderr)
        return 2
    panos = find_panoramas(args.panoramas)
    if not panos:
        print(f"error: no panoramas in {args.panoramas}", file=sys.stderr)
        return 2
    yaw_table = read_yaw_csv(args.yaw_csv) if args.yaw_csv else None

    records = []  # (name, path, yaw, manhattan_known, group)
    excluded = []
    for name, path in panos:
        yaw, known, group = 0.0, bool(args.aligned), name
        if yaw_table is not None and name in yaw_table.index:
            row = yaw_table.loc[name]
            yaw, known = float(row["manhattan_yaw_deg"]), bool(row["manhattan"])
            if args.group_by == "room":
                group = str(row["group"])
            if not known and args.non_manhattan == "exclude":
                excluded.append(name)
                continue
        records.append((name, path, yaw, known, group))
    if not records:
        print("error: every panorama was excluded", file=sys.stderr)
        return 2
    split_of = split_groups([r[4] for r in records], args.test_fraction, args.seed)

    out: Path = args.out
    (out / "images").mkdir(parents=True, exist_ok=True)
    w, h = args.size
    cx, cy = image_centre(w, h)  # the renderer's principal point (fr_eval.datasets.panorama)
    rows, sheet_imgs, sheet_caps, yaw_rows = [], [], [], []
    for name, path, yaw, known, group in tqdm(records, desc="panoramas", disable=args.quiet):
        pano = load_any_panorama(path, args.device)
        rng = pano_rng(args.seed, name)
        ang = sample_views(rng, args.views_per_pano, fovs, args.uniform_fov,
                           pitch=args.pitch_range, roll=args.roll_range)
        R = rotation_from_angles(torch.as_tensor(ang["pan_deg"]), torch.as_tensor(ang["pitch_deg"]),
                                 torch.as_tensor(ang["roll_deg"]))
        focal = focal_from_hfov(torch.as_tensor(ang["hfov_deg"]), w)
        distortion_k = None if args.k_range is None else view_distortions(args.seed, name, len(R), args.k_range)
        views = render_views(pano, R, focal, size=(w, h), manhattan_yaw_deg=yaw, device=args.device,
                             mode=args.interp, distortion_k=distortion_k)
        hz = horizon_angles(R)
        for k in range(len(views)):
            fname = f"images/{name}_v{k:02d}.{args.format}"
            save_rgb(out / fname, views[k])
            row = {"file": fname, "pano": name, "group": group, "split": split_of[group], "width": w, "height": h,
                   "cx": cx, "cy": cy, "focal_px": float(focal[k]), "hfov_deg": float(ang["hfov_deg"][k]),
                   "pan_deg": float(ang["pan_deg"][k]), "tilt_deg": float(hz["tilt_deg"][k]),
                   "roll_deg": float(hz["roll_deg"][k]), "pitch_deg": float(hz["pitch_deg"][k]),
                   "manhattan_known": known, "manhattan_yaw_deg": yaw}
            row.update({c: float(v) for c, v in zip(R_COLUMNS, R[k].reshape(-1).tolist())})
            if distortion_k is not None:
                row["k"] = float(distortion_k[k])
            rows.append(row)
            if len(sheet_imgs) < args.sheet_views and k % max(1, args.views_per_pano // 5) == 0:
                sheet_imgs.append(views[k])
                sheet_caps.append(f"{name[-28:]} v{k}\nFOV {row['hfov_deg']:.0f}  tilt {row['tilt_deg']:+.1f}"
                                  f"  roll {row['roll_deg']:+.1f}")
        if args.check_yaw and known:
            res = yaw_check(pano, yaw, device=args.device)
            yaw_rows.append({"pano": name, "manhattan_yaw_deg": yaw, **res})

    gt = pd.DataFrame(rows)
    gt[GT_COLUMNS + (["k"] if args.k_range is not None else [])].to_csv(out / "gt.csv", index=False,
                                                                       float_format="%.10g")
    contact_sheet(sheet_imgs, sheet_caps, out / "contact_sheet.png")
    if yaw_rows:
        pd.DataFrame(yaw_rows).to_csv(out / "yaw_check.csv", index=False, float_format="%.4f")

    summary = {}
    for split in ("train", "test"):
        sub = gt[gt["split"] == split]
        summary[split] = {"panoramas": int(sub["pano"].nunique()), "groups": int(sub["group"].nunique()),
                          "views": int(len(sub))}
    meta = {
        "generator": "fr_eval.datasets.make_dataset (fr make-dataset)",
        "command": " ".join(sys.argv),
        "panoramas_dir": str(args.panoramas), "yaw_csv": str(args.yaw_csv) if args.yaw_csv else None,
        "aligned": bool(args.aligned), "non_manhattan": args.non_manhattan, "excluded_panoramas": excluded,
        "views_per_pano": args.views_per_pano, "fovs_deg": fovs,
        "uniform_fov_deg": list(args.uniform_fov) if args.uniform_fov else None,
        "size": [w, h], "seed": args.seed,
        "distortion": None if args.k_range is None else {
            "model": "division (fr_torch.core.geometry.lens), centre the principal point", "k_range": list(args.k_range)}, "test_fraction": args.test_fraction, "group_by": args.group_by,
        "pan_range_deg": [-180.0, 180.0], "pitch_range_deg": list(args.pitch_range),
        "roll_range_deg": list(args.roll_range), "interp": args.interp, "format": args.format,
        "principal_point": "the image centre ((w-1)/2, (h-1)/2) (gt.csv cx, cy), pixel (0,0) centre at (0,0)",
        "rotation": "world->camera, room Manhattan frame when manhattan_known else panorama frame; "
                    "R.T = Ry(pan) Rx(pitch) Rz(roll); vertical (down) in column 1",
        "angles": "the sampled range applies to the pitch; tilt/roll/pitch in gt.csv from fr_torch.core.geometry.conventions.horizon_angles",
        "summary": summary, "seconds": round(time.time() - t0, 1),
    }
    (out / "dataset.json").write_text(json.dumps(meta, indent=2))
    if not args.quiet:
        print(f"wrote {len(gt)} views of {gt['pano'].nunique()} panoramas to {out} in {meta['seconds']} s; "
              + "; ".join(f"{s}: {v['panoramas']} panos / {v['groups']} groups / {v['views']} views"
                          for s, v in summary.items())
              + (f"; excluded {len(excluded)}: {', '.join(excluded)}" if excluded else ""))
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="fr make-dataset", description=__doc__.split("\n")[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())
