"""Online recalibration from a stream of frames: ``fr track SOURCE`` and :class:`OnlineCalibrator`.

Python use::

    from fr_torch import FREstimator
    from fr_torch.reliability import ReliabilityModel
    from fr_torch.track import OnlineCalibrator

    est, rel = FREstimator(mode="fast"), ReliabilityModel.load_default("fast")
    tracker = OnlineCalibrator()
    for result in est.calibrate_images(frames):
        rel.annotate(result, "fast")            # predicted errors -> result.predicted_error
        state = tracker.update(result)          # FusedState: focal_px, rotation, roll/tilt, ...

Fusion (one *segment* = the frames since the last restart)
----------------------------------------------------------
* A frame is **rejected** when the estimate failed or ``result.reliable`` is False (too few
  segments, non-Manhattan scene, or a predicted error above the thresholds of
  ``configs/reliability.json``).
* Each accepted frame carries predicted absolute errors ``e`` (roll, tilt in deg, focal in %; a
  missing prediction counts as the thresholds).  Predicted *mean absolute* errors are turned into
  standard deviations ``s = e * sqrt(pi / 2)`` (Gaussian), floored at ``min_sigma``.
* **Rotation**: the frame's R is first mapped to the representative of its Manhattan frame that
  is closest to the fused R (the 24 proper signed permutations P of the columns, ``R P``; chordal
  distance), then fused by the weighted **chordal L2 mean on SO(3)**: ``M = sum_i w_i R_i`` and
  ``R = U diag(1, 1, det(U V^T)) V^T`` from the SVD ``M = U S V^T``, with
  ``w_i = 1 / (s_roll^2 + s_tilt^2)``.  Euler angles are never averaged.
* **Focal length**: weighted mean of ``ln f`` with ``w_i = 1 / s_focal^2`` (s as a fraction).
* Old frames are forgotten exponentially: all weights are multiplied by ``1 - 1/memory`` at each
  accepted frame, so the fused state follows a slowly drifting camera (``memory`` frames).
* The fused standard deviations are ``1 / sqrt(sum w)`` (independent errors assumed -- optimistic
  for errors that are correlated across frames of one scene), floored at ``min_sigma``.
* **Camera moved**: an accepted frame *disagrees* with the fused state when, for roll, tilt,
  focal (%) or the rotation angle after symmetry resolution, ``|difference| > change_k *
  sqrt(s_frame^2 + s_fused^2)``.  Disagreeing frames are held back (not fused); when ``patience``
  consecutive accepted frames disagree with the fused state but agree with each other, fusion
  restarts from them (``restarted`` is True on that frame, ``segment`` increments).  A single
  disagreeing frame followed by an agreeing one is an outlier and is dropped.

Outputs of ``fr track`` (``--out``, default ``track_<source name>/``): ``frames.csv`` (one row per
processed frame: estimate, predicted errors, status, fused state after the frame),
``calibration.json`` (the final fused calibration, restarts and settings) and ``track.png`` (per
frame estimates with predicted error bars, rejected frames, fused track, restarts).
"""
from __future__ import annotations

import argparse
import itertools
import json
import math
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np

IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm"}
SIGMA_FROM_MAE = math.sqrt(math.pi / 2.0)  # Gaussian: std = MAE * sqrt(pi / 2)


def manhattan_symmetries() -> np.ndarray:
    """The 24 proper signed permutation matrices (3x3, det +1): the symmetries of a Manhattan frame."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            p = np.zeros((3, 3))
            for col, (row, s) in enumerate(zip(perm, signs)):
                p[row, col] = s
            if np.linalg.det(p) > 0:
                out.append(p)
    return np.stack(out)


SYMMETRIES = manhattan_symmetries()


def align_to(rotation: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """The equivalent Manhattan frame ``rotation @ P`` closest (chordal) to ``reference``."""
    candidates = rotation[None] @ SYMMETRIES  # (24, 3, 3)
    return candidates[int(np.argmax(np.einsum("kij,ij->k", candidates, reference)))]


def project_so3(m: np.ndarray) -> np.ndarray:
    """Closest rotation (Frobenius) to a 3x3 matrix: the chordal L2 mean when m = sum w_i R_i."""
    u, _, vt = np.linalg.svd(m)
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    return u @ np.diag([1.0, 1.0, d]) @ vt


def rotation_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    cos = (np.trace(a.T @ b) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def camera_angles(rotation: np.ndarray) -> dict[str, float]:
    """roll / tilt / pitch / pan (deg) of a world->camera R with the project's definitions."""
    import torch

    from .camera import angles_from_rotation

    angles = angles_from_rotation(torch.as_tensor(np.asarray(rotation, np.float64)))
    return {k: float(v) for k, v in angles.items()}


@dataclass
class FrameEstimate:
    """What the calibrator needs from one frame (built from a CalibrationResult)."""

    index: int
    ok: bool
    reliable: bool
    focal_px: float | None = None
    rotation: np.ndarray | None = None
    roll_deg: float | None = None
    tilt_deg: float | None = None
    predicted_error: dict[str, float] | None = None
    reason: str = ""


@dataclass
class FusedState:
    """Fused calibration after a frame.  ``status`` of that frame: ``fused``, ``started``,
    ``restarted``, ``rejected`` (unreliable), ``held`` (disagrees: possible camera move / outlier)."""

    frame: int
    status: str
    segment: int
    n_fused: int = 0
    focal_px: float | None = None
    rotation: np.ndarray | None = None
    roll_deg: float | None = None
    tilt_deg: float | None = None
    pitch_deg: float | None = None
    pan_deg: float | None = None
    sigma: dict[str, float] | None = None  # fused standard deviations: roll_deg, tilt_deg, focal_pct
    restarted: bool = False
    disagreement: float | None = None  # largest normalised difference frame vs fused (units of change_k)

    @property
    def valid(self) -> bool:
        return self.focal_px is not None

    def to_json(self) -> dict[str, Any]:
        out = asdict(self)
        if self.rotation is not None:
            out["rotation"] = np.asarray(self.rotation).tolist()
        return out


@dataclass
class OnlineCalibrator:
    """Fuses per-frame fR estimates into a current calibration; see the module docstring."""

    memory: float = 30.0
    change_k: float = 3.0
    patience: int = 2
    min_sigma: dict[str, float] = field(default_factory=lambda: {"roll_deg": 0.2, "tilt_deg": 0.2, "focal_pct": 1.0})
    default_error: dict[str, float] | None = None  # used when a frame has no predicted error (thresholds)
    history: list[FusedState] = field(default_factory=list, init=False)

    def __post_init__(self) -> None:
        if self.default_error is None:
            from .reliability import load_thresholds

            self.default_error = load_thresholds()
        self.reset()
        self.segment = -1

    # ------------------------------------------------------------------ state

    def reset(self) -> None:
        self._m = np.zeros((3, 3))  # sum of w_rot * aligned R
        self._w_rot = 0.0
        self._logf = 0.0  # sum of w_f * ln f
        self._w_f = 0.0
        self._w_roll = self._w_tilt = 0.0  # precisions for the reported sigmas
        self._n = 0
        self._pending: list[FrameEstimate] = []
        self.rotation: np.ndarray | None = None
        self.focal_px: float | None = None
        self._frame = -1

    def _sigmas(self, e: FrameEstimate) -> dict[str, float]:
        pred = dict(self.default_error)
        if e.predicted_error:
            pred.update({k: v for k, v in e.predicted_error.items() if v is not None and math.isfinite(v)})
        return {k: max(self.min_sigma[k], SIGMA_FROM_MAE * pred[k]) for k in ("roll_deg", "tilt_deg", "focal_pct")}

    def fused_sigma(self) -> dict[str, float] | None:
        if self._n == 0:
            return None
        return {"roll_deg": max(self.min_sigma["roll_deg"], 1 / math.sqrt(self._w_roll)),
                "tilt_deg": max(self.min_sigma["tilt_deg"], 1 / math.sqrt(self._w_tilt)),
                "focal_pct": max(self.min_sigma["focal_pct"], 100 / math.sqrt(self._w_f))}

    def _add(self, e: FrameEstimate) -> None:
        s = self._sigmas(e)
        decay = 1.0 - 1.0 / self.memory if self._n else 0.0
        rotation = e.rotation if self.rotation is None else align_to(e.rotation, self.rotation)
        w_rot = 1.0 / (s["roll_deg"] ** 2 + s["tilt_deg"] ** 2)
        w_f = 1.0 / (s["focal_pct"] / 100.0) ** 2
        self._m = decay * self._m + w_rot * rotation
        self._w_rot = decay * self._w_rot + w_rot
        self._logf = decay * self._logf + w_f * math.log(e.focal_px)
        self._w_f = decay * self._w_f + w_f
        self._w_roll = decay * self._w_roll + 1.0 / s["roll_deg"] ** 2
        self._w_tilt = decay * self._w_tilt + 1.0 / s["tilt_deg"] ** 2
        self._n += 1
        self.rotation = project_so3(self._m)
        self.focal_px = math.exp(self._logf / self._w_f)

    def disagreement(self, e: FrameEstimate, rotation: np.ndarray, focal_px: float, sigma: dict | None) -> float:
        """Largest |difference| / sqrt(s_frame^2 + s_ref^2) over roll, tilt, focal and rotation angle."""
        s = self._sigmas(e)
        ref = sigma or s
        aligned = align_to(e.rotation, rotation)
        angles = camera_angles(rotation)
        mine = camera_angles(aligned)  # the frame's angles in the reference's labelling of the axes
        roll, tilt = mine["roll_deg"], mine["tilt_deg"]
        z = [abs(roll - angles["roll_deg"]) / math.hypot(s["roll_deg"], ref["roll_deg"]),
             abs(tilt - angles["tilt_deg"]) / math.hypot(s["tilt_deg"], ref["tilt_deg"]),
             100 * abs(e.focal_px - focal_px) / focal_px / math.hypot(s["focal_pct"], ref["focal_pct"]),
             rotation_angle_deg(aligned, rotation) / math.hypot(math.hypot(s["roll_deg"], s["tilt_deg"]),
                                                                math.hypot(ref["roll_deg"], ref["tilt_deg"]))]
        return max(z)

    # ------------------------------------------------------------------ update

    @staticmethod
    def frame_from_result(result, index: int) -> FrameEstimate:
        ok = bool(getattr(result, "ok", False)) and getattr(result, "rotation", None) is not None
        return FrameEstimate(index=index, ok=ok, reliable=ok and bool(result.reliable),
                             focal_px=result.focal_px if ok else None,
                             rotation=np.asarray(result.rotation, np.float64) if ok else None,
                             roll_deg=result.roll_deg if ok else None, tilt_deg=result.tilt_deg if ok else None,
                             predicted_error=result.predicted_error, reason=result.reason)

    def update(self, result, index: int | None = None) -> FusedState:
        """Feed one frame's CalibrationResult (annotated with predicted errors); returns the fused state."""
        self._frame = self._frame + 1 if index is None else int(index)
        e = result if isinstance(result, FrameEstimate) else self.frame_from_result(result, self._frame)
        restarted, z = False, None
        if not (e.ok and e.reliable):
            status = "rejected"
        elif self._n == 0:
            self.segment += 1
            self._add(e)
            status = "started"
        else:
            z = self.disagreement(e, self.rotation, self.focal_px, self.fused_sigma()) / self.change_k
            if z <= 1.0:
                self._add(e)
                self._pending.clear()
                status = "fused"
            else:
                # keep only the held-back frames that agree with this one (consecutive run)
                self._pending = [p for p in self._pending
                                 if self.disagreement(p, e.rotation, e.focal_px, self._sigmas(e)) <= self.change_k]
                self._pending.append(e)
                status = "held"
                if len(self._pending) >= self.patience:
                    pending = self._pending
                    self.reset()
                    self.segment += 1
                    for p in pending:
                        self._add(p)
                    status, restarted = "restarted", True
        state = self.state(status)
        state.restarted, state.disagreement = restarted, z
        self.history.append(state)
        return state

    def state(self, status: str = "fused") -> FusedState:
        if self._n == 0:
            return FusedState(frame=self._frame, status=status, segment=self.segment)
        a = camera_angles(self.rotation)
        return FusedState(frame=self._frame, status=status, segment=self.segment, n_fused=self._n,
                          focal_px=self.focal_px, rotation=self.rotation.copy(), roll_deg=a["roll_deg"],
                          tilt_deg=a["tilt_deg"], pitch_deg=a["pitch_deg"], pan_deg=a["pan_deg"],
                          sigma=self.fused_sigma())


# ---------------------------------------------------------------------------------- frame sources

def iter_frames(source: str | Path, every: int = 1, max_frames: int | None = None) -> Iterator[tuple[int, str, np.ndarray]]:
    """(frame index, name, BGR/grey image) from a folder of images (sorted names) or a video file."""
    import cv2

    from .segments import FRInputError, load_image

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
            "status": state.status, "segment": state.segment, "restarted": state.restarted,
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

def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("source", type=Path, help="video file or folder of frames (sorted by name)")
    parser.add_argument("--out", type=Path, default=None, help="output folder (default track_<source name>)")
    parser.add_argument("--every", type=int, default=1, metavar="N", help="process every N-th frame")
    parser.add_argument("--max-frames", type=int, default=None, help="stop after this many processed frames")
    parser.add_argument("--batch-size", type=int, default=8, help="frames searched together")
    parser.add_argument("--fast", action="store_true", help="Fast-fR (10 refinement iterations)")
    parser.add_argument("--detector", default="lsd")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--memory", type=float, default=30.0, help="fusion memory in accepted frames (forgetting)")
    parser.add_argument("--change-k", type=float, default=3.0, help="camera-moved threshold in predicted sigmas")
    parser.add_argument("--patience", type=int, default=2,
                        help="consecutive disagreeing reliable frames that mean the camera moved")
    parser.add_argument("--no-reliability", action="store_true",
                        help="ignore the reliability model (constant weights = thresholds)")


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from .estimator import FREstimator
    from .reliability import ReliabilityModel
    from . import validate
    from .segments import FRInputError

    if args.every < 1 or args.batch_size < 1:
        raise FRInputError("--every and --batch-size must be at least 1")
    validate.track_options(args)
    mode = "fast" if args.fast else "fr"
    estimator = FREstimator(mode=mode, detector=args.detector, device=args.device)
    model = None if args.no_reliability else ReliabilityModel.load_default(mode)
    if model is None and not args.no_reliability:
        print(f"fr track: no reliability model for {mode}: all reliable frames weigh the same", file=sys.stderr)
    tracker = OnlineCalibrator(memory=args.memory, change_k=args.change_k, patience=args.patience)
    out = args.out or Path(f"track_{args.source.stem or args.source.name}")
    out.mkdir(parents=True, exist_ok=True)
    rows, batch = [], []

    def flush():
        results = estimator.calibrate_images([im for _, _, im in batch], names=[n for _, n, _ in batch])
        for (index, name, _), result in zip(batch, results):
            if model is not None and result.ok:
                model.annotate(result, mode)
            state = tracker.update(result, index)
            rows.append(frame_row(index, name, result, state))
            if state.restarted:
                print(f"fr track: camera moved at frame {index}: fusion restarted", file=sys.stderr)
        batch.clear()

    bar = tqdm(desc="fr track", unit="frame", file=sys.stderr)
    for item in iter_frames(args.source, args.every, args.max_frames):
        batch.append(item)
        if len(batch) >= args.batch_size:
            flush()
            bar.update(args.batch_size)
    if batch:
        bar.update(len(batch))
        flush()
    bar.close()
    if not rows:
        raise FRInputError(f"{args.source}: no frame could be read (all skipped)")

    import pandas as pd

    pd.DataFrame(rows).to_csv(out / "frames.csv", index=False)
    final = tracker.history[-1] if tracker.history else None
    summary = {"source": str(args.source), "mode": mode, "frames_processed": len(rows),
               "frames_accepted": sum(r["status"] in ("fused", "started", "restarted") for r in rows),
               "frames_rejected": sum(r["status"] == "rejected" for r in rows),
               "restarts_at_frames": [r["frame"] for r in rows if r["restarted"]],
               "reliability_model": model is not None,
               "settings": {"every": args.every, "memory": args.memory, "change_k": args.change_k,
                            "patience": args.patience},
               "calibration": final.to_json() if final is not None and final.valid else None}
    if summary["calibration"] is not None:
        from .camera import hfov_from_focal

        width = next(r["width"] for r in reversed(rows) if r["ok"])
        summary["calibration"]["hfov_deg"] = hfov_from_focal(final.focal_px, width)
    (out / "calibration.json").write_text(json.dumps(summary, indent=1) + "\n")
    plot_track(rows, out / "track.png", f"fr track {args.source.name} ({mode})")
    print(json.dumps({k: summary[k] for k in ("frames_processed", "frames_accepted", "restarts_at_frames")}))
    print(f"fr track: wrote {out / 'frames.csv'}, {out / 'calibration.json'}, {out / 'track.png'}", file=sys.stderr)
    return 0 if summary["calibration"] is not None else 1
