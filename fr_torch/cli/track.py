"""``fr track``: the command-line front end of :mod:`fr_torch.video.track`."""
from __future__ import annotations

import argparse
import json
import sys
from collections import deque
from pathlib import Path

import pandas as pd
from tqdm import tqdm

from fr_torch.cli.options import (
    add_estimator_arguments,
    device_policy,
    estimator_kwargs,
)
from fr_torch.core.checks import finite_number, positive_int, positive_number
from fr_torch.errors import FRInputError
from fr_torch.runtime.estimator import FREstimator
from fr_torch.runtime.pipeline import calibrate_stream
from fr_torch.runtime.workers import start_worker_server
from fr_torch.video.fusion import OnlineCalibrator
from fr_torch.video.track import frame_row, iter_frames, plot_track


def track_options(args) -> None:
    """``fr track`` options: memory >= 1 frame, change_k > 0, patience >= 1 (one-line errors)."""
    memory = finite_number(args.memory, "--memory")
    if memory < 1:
        raise FRInputError(f"--memory must be at least 1 frame, got {args.memory!r}")
    positive_number(args.change_k, "--change-k")
    positive_int(args.patience, "--patience")
    if args.max_frames is not None:
        positive_int(args.max_frames, "--max-frames")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``fr track``."""
    parser.add_argument("source", type=Path, help="video file or folder of frames (sorted by name)")
    parser.add_argument("--out", type=Path, default=None, help="output folder (default track_<source name>)")
    parser.add_argument("--every", type=int, default=1, metavar="N", help="process every N-th frame")
    parser.add_argument("--max-frames", type=int, default=None, help="stop after this many processed frames")
    parser.add_argument("--batch-size", type=int, default=8, help="frames searched together")
    parser.add_argument("--workers", type=int, default=0, metavar="N",
                        help="CPU: calibrate frames in N single-threaded worker processes, in order; GPU: "
                             "N processes decode and detect frames ahead of the search (default 0: this "
                             "process; worth it for long videos on many cores)")
    add_estimator_arguments(parser)  # the estimator options shared with fr calibrate and fr batch
    parser.add_argument("--memory", type=float, default=30.0, help="fusion memory in accepted frames (forgetting)")
    parser.add_argument("--change-k", type=float, default=3.0, help="camera-moved threshold in predicted sigmas")
    parser.add_argument("--patience", type=int, default=2,
                        help="consecutive disagreeing reliable frames that mean the camera moved")
    parser.add_argument("--no-reliability", action="store_true",
                        help="ignore the reliability stage: frames kept on the sanity checks alone, not the "
                             "reliable promise, and weighed the same (fR then skips the focal_profile_gap cue, a "
                             "quarter of its time)")


def run(args: argparse.Namespace) -> int:
    if args.every < 1 or args.batch_size < 1:
        raise FRInputError("--every and --batch-size must be at least 1")
    if args.workers < 0:
        raise FRInputError("--workers must be 0 (this process) or more")
    policy = device_policy(args)
    if args.workers:
        start_worker_server()
    policy.apply_threads()
    track_options(args)
    estimator = FREstimator(**estimator_kwargs(args), reliability=None if args.no_reliability else "default")
    mode = estimator.mode
    scope_gap = estimator.reliability_scope_gap(detected=True) if estimator.reliability is not None else None
    if scope_gap is not None:  # its "not reliable" would reject every frame: track without it
        estimator = FREstimator(**estimator_kwargs(args), reliability=None)
        print(f"fr track: {scope_gap}: all reliable frames weigh the same", file=sys.stderr)
    model = estimator.reliability
    if model is None and not args.no_reliability and scope_gap is None:
        print(f"fr track: no reliability model for {mode}: all reliable frames weigh the same", file=sys.stderr)
    tracker = OnlineCalibrator(memory=args.memory, change_k=args.change_k, patience=args.patience)
    out = args.out or Path(f"track_{args.source.stem or args.source.name}")
    out.mkdir(parents=True, exist_ok=True)

    rows, indices = [], deque()

    def frames():  # (image, name) for the estimator; the frame indices wait here, in order
        for index, name, image in iter_frames(args.source, args.every, args.max_frames):
            indices.append(index)
            yield image, name

    bar = tqdm(desc="fr track", unit="frame", file=sys.stderr)
    try:
        for result in calibrate_stream(estimator, frames(), args.batch_size, args.workers):
            index = indices.popleft()
            state = tracker.update(result, index)
            rows.append(frame_row(index, result.image, result, state))
            if state.restarted:
                bar.write(f"fr track: camera moved at frame {index}: fusion restarted", file=sys.stderr)
            bar.update(1)
    finally:
        bar.close()
    if not rows:
        raise FRInputError(f"{args.source}: no frame could be read (all skipped)")

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
        summary["calibration"]["hfov_deg"] = final.hfov_deg  # of the fused camera (the video's frame width)
    (out / "calibration.json").write_text(json.dumps(summary, indent=1) + "\n")
    plot_track(rows, out / "track.png", f"fr track {args.source.name} ({mode})")
    print(json.dumps({k: summary[k] for k in ("frames_processed", "frames_accepted", "restarts_at_frames")}))
    print(f"fr track: wrote {out / 'frames.csv'}, {out / 'calibration.json'}, {out / 'track.png'}", file=sys.stderr)
    return 0 if summary["calibration"] is not None else 1
