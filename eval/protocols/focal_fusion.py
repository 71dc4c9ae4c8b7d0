"""Focal fusion over many photos of one camera: does weighting by predicted errors help?

    python -m fr_eval.protocols.focal_fusion results/yud/predictions.csv --out results/reliability/focal_fusion.md

YorkUrbanDB's photos were all taken with one camera (f = 674.9 px), so fusing their focal estimates
is what ``fr track`` does for a fixed camera, without the rotations (each photo shows another
scene).  For each method (``fr``, ``fast-fr``) the estimates of the CSV (``fr eval``'s per-image
predictions, which carry the cues) are fused three ways, each a weighted mean of ``ln f``:

* ``unweighted``: every estimate counts the same;
* ``paper cues``: weights ``1 / s^2`` from :meth:`fr_torch.video.fusion.OnlineCalibrator.frame_sigmas`
  (``fr track``'s rule), s from the focal error predicted by a model of the paper's three cues,
  trained here exactly as the shipped one (``fr train-reliability``: the same cached train records
  of the shipped model's training datasets, ``--records``, same K search) but with
  ``cue_names = PAPER_CUE_NAMES``;
* ``shipped model``: the same with the shipped model (``configs/reliability_<mode>.npz``: fR's
  uses all six cues, Fast-fR's the paper's and ``focal_prior_share``).

Only frames ``fr track`` would accept count (``ok`` and ``reliable``; the ``reliable`` column of the
CSV comes from the shipped model).  Reported: the fused focal length's error (%) against the
camera's true focal length, and how many frames were fused.  The images must share one true focal
length (checked).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from fr_eval.protocols.reliability_train import DEFAULT_RECORDS, fit_model, usable
from fr_torch.core.reliability.model import PAPER_CUE_NAMES, ReliabilityModel
from fr_torch.video.fusion import OnlineCalibrator

MODES = {"fr": "fr", "fast-fr": "fast"}


def paper_cue_model(mode: str, records: Path, sources) -> ReliabilityModel:
    """A model of the paper's three cues, fitted on the cached train records of ``sources`` (the
    shipped model's training datasets, ``meta["training_data"]``)."""
    frames = [pd.read_csv(records / f"{source}_train_{mode}.csv") for source in sources]
    train = usable(pd.concat(frames, ignore_index=True), PAPER_CUE_NAMES)
    return fit_model(train, PAPER_CUE_NAMES, meta={"mode": mode})


def fused_focal_error_pct(focal_px: np.ndarray, predicted_focal_pct: np.ndarray | None, true_focal_px: float) -> float:
    """|exp(weighted mean of ln f) - true| / true, %; ``predicted_focal_pct`` None = equal weights."""
    if predicted_focal_pct is None:
        weights = np.ones(len(focal_px))
    else:
        calibrator = OnlineCalibrator()
        sigma = np.array([calibrator.frame_sigmas({"focal_pct": e})["focal_pct"] for e in predicted_focal_pct])
        weights = 1.0 / (sigma / 100.0) ** 2
    fused = np.exp((weights * np.log(focal_px)).sum() / weights.sum())
    return float(100.0 * abs(fused - true_focal_px) / true_focal_px)


def fuse(predictions: pd.DataFrame, records: Path) -> pd.DataFrame:
    rows = []
    for method, mode in MODES.items():
        d = predictions[(predictions["method"] == method) & ~predictions["failed"].astype(bool)
                        & predictions["reliable"].astype(bool)]
        if d.empty:
            continue
        truth = d["gt_focal_px"].to_numpy(float)
        if not np.allclose(truth, truth[0], rtol=1e-9):
            raise ValueError(f"{method}: the images do not share one true focal length")
        shipped = ReliabilityModel.load_default(mode)
        paper = paper_cue_model(mode, records, shipped.meta["training_data"])
        focal = d["est_focal_px"].to_numpy(float)
        cue = {name: d[f"cue_{name}"].to_numpy(float) for name in shipped.cue_names}
        predicted = {"paper cues": paper.predict(np.stack([cue[n] for n in PAPER_CUE_NAMES], 1))[:, 2],
                     "shipped model": shipped.predict(np.stack([cue[n] for n in shipped.cue_names], 1))[:, 2]}
        row = {"method": method, "frames": len(d), "true_focal_px": float(truth[0]),
               "unweighted": fused_focal_error_pct(focal, None, truth[0])}
        row.update({name: fused_focal_error_pct(focal, p, truth[0]) for name, p in predicted.items()})
        rows.append(row)
    return pd.DataFrame(rows)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("predictions", type=Path, help="fr eval's predictions.csv (images of one camera)")
    parser.add_argument("--records", type=Path, default=DEFAULT_RECORDS,
                        help="cached train records of fr train-reliability (for the paper-cue model)")
    parser.add_argument("--out", type=Path, default=None, help="also write this Markdown table")
    args = parser.parse_args(argv)
    table = fuse(pd.read_csv(args.predictions), args.records)
    print(table.to_string(index=False, float_format=lambda v: f"{v:.2f}"))
    if args.out:
        lines = ["# Focal fusion over one camera's photos", "",
                 f"Command: `python -m fr_eval.protocols.focal_fusion {args.predictions}` (module docstring: method).  "
                 "Error (%) of the fused focal length (weighted mean of ln f over the frames `fr track` would "
                 "accept) against the camera's true focal length; weights 1/s^2 from the predicted focal error "
                 "(`OnlineCalibrator.frame_sigmas`).", "",
                 "| method | frames | unweighted | weighted, paper cues "
                 "| weighted, shipped model (fR: all six cues; Fast-fR: paper cues + focal_prior_share) |",
                 "|---|---:|---:|---:|---:|"]
        for _, r in table.iterrows():
            lines.append(f"| {r['method']} | {r['frames']} | {r['unweighted']:.2f} | {r['paper cues']:.2f} | "
                         f"{r['shipped model']:.2f} |")
        args.out.write_text("\n".join(lines) + "\n")
        print(f"wrote {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
