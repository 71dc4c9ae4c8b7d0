"""Every field of fR's and Fast-fR's results on a few photos, saved or compared bit for bit.

``python tools/bit_identity.py save out.npz`` / ``... compare out.npz``: YUD train photos (LSD
segments, detected once and cached next to the output) and synthetic scenes, calibrated in one batch
and one by one, in both modes, in one batch with the division model's lens search
(``distortion="division"``), and with extra horizontal families (``families="auto"``, batched
and one by one); every field of the results, the error bounds and both promises included;
``compare`` prints every field that differs in a single bit (exit 1).
Save with one checkout (``PYTHONPATH=<it>``), compare with another.
``--photos``, ``--synthetic``: how many of each.  ``--device cuda``: the estimators on a GPU (save
and compare there for run-to-run identity); ``report`` compares without failing and sums up how far
the two sides are apart (a CPU save against a GPU run: how many fields differ, by how much, and
which flags).  ``--segments PATH``: the segments' cache (default: beside the output), so that a
machine without the photos (the lent GPU) reads the ones detected here.  ``--against SAVE``: compare
or report two saves, calibrating nothing.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch


def segment_sets(cache: Path, photos: int, synthetic: int):
    if cache.is_file():
        data = np.load(cache, allow_pickle=True)
        return list(data["segments"]), [tuple(s) for s in data["sizes"]]
    from fr_eval.datasets.registry import detected_segments, load_dataset
    from fr_torch.detectors.lsd import LSDDetector
    from fr_torch.synthetic import random_rotation, synthetic_segments
    detector = LSDDetector()
    segments, sizes = [], []
    for sample in load_dataset("yud", split="train")[:photos]:
        segments.append(np.asarray(detected_segments(sample, detector), dtype=np.float32))
        sizes.append((sample.width, sample.height))
    rng = np.random.default_rng(60)
    for _ in range(synthetic):
        out = synthetic_segments(float(rng.uniform(400, 900)), random_rotation(rng), seed=int(rng.integers(1 << 30)))
        segments.append(np.asarray(out[0] if isinstance(out, tuple) else out, dtype=np.float32))
        sizes.append((640, 480))
    holder = np.empty(len(segments), dtype=object)
    holder[:] = segments
    np.savez(cache, segments=holder, sizes=np.array(sizes))
    return segments, sizes


def flatten(prefix: str, result, out: dict) -> None:
    for name in ("focal_px", "rotation", "log_likelihood", "principal_point", "labels", "ranked_vanishing_points",
                 "vanishing_point_support", "manhattan_fraction", "ok", "reliable", "reason", "distortion_k", "model",
                 "horizon_reliable", "horizon_reason"):
        value = getattr(result, name, None)
        out[f"{prefix}/{name}"] = np.asarray(value if value is not None else np.nan)
    for group in ("cues", "predicted_error", "error_bound"):
        for key, value in sorted((getattr(result, group) or {}).items()):
            if isinstance(value, dict):  # the bounds' limits
                for inner, limit in sorted(value.items()):
                    out[f"{prefix}/{group}/{key}/{inner}"] = np.asarray(limit)
            else:
                out[f"{prefix}/{group}/{key}"] = np.asarray(value if value is not None else np.nan)


def run(segments, sizes, device: str = "cpu") -> dict:
    from fr_torch import FREstimator, SearchConfig
    out = {}
    for mode in ("fast", "fr"):
        estimator = FREstimator(mode=mode, device=device)
        batched = estimator.calibrate_segments(segments, sizes)
        for i, result in enumerate(batched):
            flatten(f"{mode}/batch/{i}", result, out)
        for i in range(len(segments)):
            [result] = estimator.calibrate_segments([segments[i]], [sizes[i]])
            flatten(f"{mode}/single/{i}", result, out)
    for mode in ("fast", "fr"):  # the lens searched too (the division model's k), one batch
        batched = FREstimator(mode=mode, distortion="division", device=device).calibrate_segments(segments, sizes)
        for i, result in enumerate(batched):
            flatten(f"{mode}-division/batch/{i}", result, out)
    for mode in ("fast", "fr"):  # extra horizontal families, batched and one by one
        estimator = FREstimator(mode=mode, search_config=SearchConfig.from_config(families="auto"), device=device)
        for i, result in enumerate(estimator.calibrate_segments(segments, sizes)):
            flatten(f"{mode}-families/batch/{i}", result, out)
        for i in range(len(segments)):
            [result] = estimator.calibrate_segments([segments[i]], [sizes[i]])
            flatten(f"{mode}-families/single/{i}", result, out)
    return out


def report(ref, out: dict, bad: list[str]) -> None:
    """How far apart the differing fields are: per kind of field (its name without the image index), how
    many differ and the largest difference (relative for numbers; flags and texts counted)."""
    kinds: dict[str, list] = {}
    for key in bad:
        kind = "/".join(part for part in key.split("/") if not part.isdigit())  # e.g. fr/batch/focal_px
        a, b = np.asarray(ref[key]), np.asarray(out[key])
        if a.dtype.kind in "fc" and a.shape == b.shape:
            both, one = np.isnan(a) & np.isnan(b), np.isnan(a) ^ np.isnan(b)  # NaN on one side only: inf
            relative = np.abs(a - b) / max(float(np.abs(a[np.isfinite(a)]).max(initial=0.0)), 1e-12)  # to the field's largest
            gap = float(np.max(np.where(both, 0.0, np.where(one, np.inf, relative)), initial=0.0))
        else:
            gap = float("nan")  # flags, labels, texts: counted only
        kinds.setdefault(kind, []).append(gap)
    for kind, gaps in sorted(kinds.items()):
        finite = [g for g in gaps if g == g]
        largest = f"largest relative difference {max(finite):.3g}" if finite else "not numbers"
        print(f"  {kind}: {len(gaps)} differ, {largest}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("action", choices=("save", "compare", "report"))
    parser.add_argument("path", type=Path)
    parser.add_argument("--photos", type=int, default=8)
    parser.add_argument("--synthetic", type=int, default=4)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--segments", type=Path, default=None)
    parser.add_argument("--against", type=Path, default=None,
                        help="compare / report: a second save instead of a run (nothing is calibrated)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if args.against is not None:
        if args.action == "save":
            parser.error("--against goes with compare or report")
        against = np.load(args.against)
        out = {key: against[key] for key in against.files}
        images = len({key.split("/")[2] for key in out if key.count("/") >= 3})
    else:
        segments, sizes = segment_sets(args.segments or args.path.with_suffix(".segments.npz"), args.photos,
                                       args.synthetic)
        out = run(segments, sizes, args.device)
        images = len(segments)
    if args.action == "save":
        np.savez(args.path, **out)
        print(f"saved {len(out)} fields of {images} images")
        return
    ref = np.load(args.path)
    unmatched = sorted(set(ref.files) ^ set(out))
    if unmatched:
        print(f"{len(unmatched)} fields only on one side (another version of this script?), e.g. {unmatched[0]}")
    bad = [k for k in sorted(set(ref.files) & set(out))
           if ref[k].shape != out[k].shape
           or (ref[k].dtype.kind in "fc" and ref[k].tobytes() != np.asarray(out[k], dtype=ref[k].dtype).tobytes())
           or (ref[k].dtype.kind not in "fc" and not np.array_equal(ref[k], out[k]))]
    print(f"compared {len(set(ref.files) & set(out))} fields of {images} images: {len(bad)} differ")
    if args.action == "report":
        report(ref, out, bad)
        return
    for k in bad[:30]:
        print("  ", k, ref[k], out[k])
    sys.exit(1 if bad or unmatched else 0)


if __name__ == "__main__":
    main()
