"""Online recalibration from a stream of frames: ``fr track SOURCE`` and :class:`OnlineCalibrator`.

Python use::

    from fr_torch import FREstimator
    from fr_torch.video.track import OnlineCalibrator

    est = FREstimator(mode="fast")              # its reliability stage fills result.predicted_error
    tracker = OnlineCalibrator()
    for result in est.calibrate_images(frames):
        state = tracker.update(result)          # FusedState: focal_px, rotation, roll/tilt, ...

Fusion: :mod:`fr_torch.video.fusion` (rejection of unreliable frames, weighted chordal mean of the
rotations, log-focal mean, forgetting, camera-moved detection and restart of a fusion *epoch*).

Outputs of ``fr track`` (``--out``, default ``track_<source name>/``): ``frames.csv`` (one row per
processed frame: estimate, predicted errors, status, fused state after the frame),
``calibration.json`` (the final fused calibration, restarts and settings) and ``track.png`` (per
frame estimates with predicted error bars, rejected frames, fused track, restarts).
"""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, Iterator, Sequence

import cv2
import numpy as np

from fr_torch.errors import FRInputError
from fr_torch.images.io import load_image
from fr_torch.video.fusion import FusedState

IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm"}

# ---------------------------------------------------------------------------------- frame sources

def iter_frames(source: str | Path, every: int = 1, max_frames: int | None = None) -> Iterator[tuple[int, str, np.ndarray]]:
    """(frame index, name, BGR/grey image) from a folder of images (sorted names) or a video file."""

    source = Path(source)
    every = max(1, int(every))
    count = 0
    if source.is_dir():
        files = sorted(p for p in source.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise FRInputError(f"{source}: no image files ({', '.join(sorted(IMAGE_SUFFIXES))})")
        for i, path in enumerate(files):
            if i % every:
                continue
            try:
                image = load_image(str(path))
            except FRInputError as exc:
                print(f"fr track: skipping {path.name}: {exc}", file=sys.stderr)
                continue
            yield i, path.name, image
            count += 1
            if max_frames and count >= max_frames:
                return
        return
    if not source.is_file():
        raise FileNotFoundError(f"{source}: no such video file or folder")
    capture = cv2.VideoCapture(str(source))
    if not capture.isOpened():
        raise FRInputError(f"{source}: OpenCV cannot open this video")
    try:
        i = 0
        while True:
            ok, image = capture.read()
            if not ok:
                break
            if i % every == 0:
                yield i, f"{source.stem}_{i:06d}", image
                count += 1
                if max_frames and count >= max_frames:
                    break
            i += 1
    finally:
        capture.release()
    if count == 0:
        raise FRInputError(f"{source}: no frames could be read")


# ---------------------------------------------------------------------------------- outputs

def frame_row(index: int, name: str, result, state: FusedState) -> dict[str, Any]:
    pred = result.predicted_error or {}
    sigma = state.sigma or {}
    return {"frame": index, "name": name, "width": result.width, "height": result.height, "ok": result.ok, "reliable": bool(result.ok and result.reliable),
            "status": state.status, "epoch": state.epoch, "restarted": state.restarted,
            "focal_px": result.focal_px, "hfov_deg": result.hfov_deg, "roll_deg": result.roll_deg,
            "tilt_deg": result.tilt_deg, "pan_deg": result.pan_deg,
            "pred_roll_err_deg": pred.get("roll_deg"), "pred_tilt_err_deg": pred.get("tilt_deg"),
            "pred_focal_err_pct": pred.get("focal_pct"),
            "fused_focal_px": state.focal_px, "fused_roll_deg": state.roll_deg, "fused_tilt_deg": state.tilt_deg,
            "fused_pan_deg": state.pan_deg, "fused_sigma_roll_deg": sigma.get("roll_deg"),
            "fused_sigma_tilt_deg": sigma.get("tilt_deg"), "fused_sigma_focal_pct": sigma.get("focal_pct"),
            "n_fused": state.n_fused, "disagreement": state.disagreement, "reason": result.reason}


def plot_track(rows: Sequence[dict], path: Path, title: str = "") -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(4, 1, figsize=(9, 9), sharex=True)
    panels = [("roll_deg", "pred_roll_err_deg", "fused_roll_deg", "roll (deg)", 1.0),
              ("tilt_deg", "pred_tilt_err_deg", "fused_tilt_deg", "tilt (deg)", 1.0),
              ("focal_px", "pred_focal_err_pct", "fused_focal_px", "focal (px)", None),
              ("pan_deg", None, "fused_pan_deg", "pan (deg, folded)", None)]
    frames = np.array([r["frame"] for r in rows], float)

    def col(key):
        return np.array([np.nan if r.get(key) is None else float(r[key]) for r in rows], float)

    good = np.array([r["status"] in ("fused", "started", "restarted") for r in rows])
    held = np.array([r["status"] == "held" for r in rows])
    rejected = ~good & ~held
    for ax, (est, err, fused, label, _) in zip(axes, panels):
        y = col(est)
        if err is not None:
            e = col(err)
            if est == "focal_px":
                e = e / 100.0 * y
            e = np.nan_to_num(e, nan=0.0)
            ax.errorbar(frames[good], y[good], yerr=e[good], fmt="o", ms=3, color="tab:blue", alpha=0.8,
                        elinewidth=0.8, label="accepted (predicted error)")
            ax.errorbar(frames[held], y[held], yerr=e[held], fmt="s", ms=3, color="tab:orange", alpha=0.8,
                        elinewidth=0.8, label="held (disagrees)")
        else:
            ax.plot(frames[good], y[good], "o", ms=3, color="tab:blue")
            ax.plot(frames[held], y[held], "s", ms=3, color="tab:orange")
        ax.plot(frames[rejected], y[rejected], "x", ms=4, color="grey", label="rejected (unreliable)")
        ax.plot(frames, col(fused), "-", color="tab:red", lw=1.5, label="fused")
        for r in rows:
            if r["restarted"]:
                ax.axvline(r["frame"], color="k", ls="--", lw=0.8)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, ncol=4, loc="best")
    axes[-1].set_xlabel("frame (dashed: camera moved, fusion restarted)")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


# ---------------------------------------------------------------------------------- CLI


