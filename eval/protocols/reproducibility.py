"""One photo, one answer: the same photos calibrated under every setting that must not change a result.

``python -m fr_eval.protocols.reproducibility run`` calibrates YUD test (LSD segments, detected once
here) and NYU-VP val (the dataset's segments) in fresh processes, one per setting, and
``... table`` compares every setting with the reference one (batch 64, in process, ``FR_THREADS=2``,
the machine's own kernel set) in ``results/reproducibility/`` (``README.md``, ``table.md``,
``rows.csv``).  Settings (:data:`SETTINGS`): batch sizes 1 / 7 / 64, worker processes 0 / 2,
``FR_THREADS`` 1 / 2, torch's CPU kernel sets ``ATEN_CPU_CAPABILITY`` = default / avx2 /
avx512 (where the CPU has it) / the native one, and an older CPU's maths libraries
(:data:`SETTING_ENV`: oneMKL, numpy and OpenBLAS pinned to the code they run on a CPU they do not
know); and ``--shared-focal`` on groups of 10 YUD test photos under every kernel set.

Per setting and mode the table gives: photos whose focal length differs at all from the
reference's, the largest relative focal difference, basin changes (focal more than 1 % or the
rotation more than 1 deg apart), ``reliable`` flips, and for the groups the spread of the shared
focal length (max / min - 1) and of its principal point (px).

``--code PATH`` runs the settings on another checkout's ``fr_torch`` (its ``PYTHONPATH``): the
table of an earlier commit, for a before/after comparison (``--label`` names it).  A setting runs
in its own process because the kernel set is chosen when torch is imported.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from fr_eval.paths import REPO

DEFAULT_OUT = REPO / "results" / "reproducibility"
#: name -> (batch size, worker processes, FR_THREADS, ATEN_CPU_CAPABILITY or None = the machine's own)
SETTINGS = {
    "reference": (64, 0, "2", None),
    "batch 1": (1, 0, "2", None),
    "batch 7": (7, 0, "2", None),
    "workers 2": (64, 2, "2", None),
    "FR_THREADS 1": (64, 0, "1", None),
    "kernels default": (64, 0, "2", "default"),
    "kernels avx2": (64, 0, "2", "avx2"),
    "kernels avx512": (64, 0, "2", "avx512"),
    "older CPU's libraries": (64, 0, "2", "default"),
}
#: Environment of a setting beyond its four fields: what another CPU's maths libraries would run,
#: pinned on this one (oneMKL's COMPATIBLE branch, numpy without AVX2 / AVX-512, OpenBLAS's oldest
#: kernels), with the oldest kernel set.
SETTING_ENV = {
    "older CPU's libraries": {"MKL_CBWR": "COMPATIBLE", "NPY_DISABLE_CPU_FEATURES": "X86_V3 X86_V4 AVX512_ICL AVX512_SPR",
                              "OPENBLAS_CORETYPE": "Prescott"},
}
SHARED_KERNELS = (None, "default", "avx2", "avx512")
GROUP_SIZE = 10
#: A photo changed basin when its focal length moved by more than this share, or its rotation by
#: more than BASIN_ROTATION_DEG.
BASIN_FOCAL = 0.01
BASIN_ROTATION_DEG = 1.0


def cpu_has(flag: str) -> bool:
    """True when /proc/cpuinfo lists ``flag`` (avx2, avx512f, ...); False where it cannot be read."""
    try:
        return flag in Path("/proc/cpuinfo").read_text().split()
    except OSError:
        return False


def native_kernels() -> str:
    """torch's own CPU kernel set on this machine, lower case (``default``, ``avx2``, ``avx512``...)."""
    import torch

    return torch.backends.cpu.get_cpu_capability().lower()


def available_settings() -> dict:
    """:data:`SETTINGS` without the kernel sets this CPU lacks and the one it runs natively (the
    reference's)."""
    lacking = {"avx2": not cpu_has("avx2"), "avx512": not cpu_has("avx512f")}
    native = native_kernels()
    return {name: s for name, s in SETTINGS.items()
            if not (s[3] and (lacking.get(s[3], False) or s[3] == native))}


def prepare_inputs(path: Path, data_root=None, limit: int | None = None) -> dict:
    """The photos every setting calibrates, saved to ``path`` (.npz): YUD test with LSD segments and
    NYU-VP val with its own; returns a summary {dataset: count}."""
    from fr_eval.datasets.registry import detected_segments, load_dataset
    from fr_torch.detectors.lsd import LSDDetector

    detector = LSDDetector()
    arrays, summary = {}, {}
    for dataset, split in (("yud", "test"), ("nyu-vp", "val")):
        samples = load_dataset(dataset, root=data_root, split=split)[:limit]
        for i, sample in enumerate(samples):
            arrays[f"{dataset}/{i}/segments"] = np.asarray(detected_segments(sample, detector), np.float64)
            arrays[f"{dataset}/{i}/meta"] = np.array([sample.width, sample.height,
                                                      sample.camera.focal_px if sample.camera else np.nan])
            arrays[f"{dataset}/{i}/name"] = np.array(sample.name)
        summary[dataset] = len(samples)
    np.savez_compressed(path, **arrays)
    return summary


def load_inputs(path: Path) -> dict:
    """{dataset: [(name, segments (N, 4), (width, height), true focal)]} from :func:`prepare_inputs`."""
    data = np.load(path)
    out: dict = {}
    keys = sorted({tuple(k.split("/")[:2]) for k in data.files}, key=lambda k: (k[0], int(k[1])))
    for dataset, i in keys:
        meta = data[f"{dataset}/{i}/meta"]
        out.setdefault(dataset, []).append((str(data[f"{dataset}/{i}/name"]), data[f"{dataset}/{i}/segments"],
                                            (int(meta[0]), int(meta[1])), float(meta[2])))
    return out


def worker(inputs: Path, out: Path, mode: str, batch: int, workers: int, shared: bool) -> None:
    """Calibrate every photo of ``inputs`` under this process's environment; write JSON lines to ``out``."""
    from fr_torch import FREstimator

    photos = load_inputs(inputs)
    estimator = FREstimator(mode=mode)
    rows = []
    if shared:
        from fr_torch.runtime.shared_focal import calibrate_shared

        yud = photos["yud"]
        for g in range(len(yud) // GROUP_SIZE):
            group = yud[g * GROUP_SIZE:(g + 1) * GROUP_SIZE]
            result = calibrate_shared(estimator, segments=[p[1] for p in group], image_sizes=[p[2] for p in group],
                                      names=[p[0] for p in group])
            rows.append({"dataset": "yud", "group": g, "focal_px": result.focal_px, "truth": group[0][3],
                         "principal_point": list(result.principal_point) if result.principal_point else None})
    else:
        from fr_torch.runtime.pipeline import calibrate_segments_sharded

        for dataset, items in photos.items():
            for b0 in range(0, len(items), batch):
                chunk = items[b0:b0 + batch]
                results = calibrate_segments_sharded(estimator, [c[1] for c in chunk], [c[2] for c in chunk],
                                                     workers, names=[c[0] for c in chunk])
                for (name, _, _, truth), r in zip(chunk, results):
                    rows.append({"dataset": dataset, "image": name, "ok": r.ok, "reliable": bool(r.reliable), "reason": r.reason,
                                 "focal_px": r.focal_px, "truth": truth,
                                 "rotation": None if r.rotation is None else np.asarray(r.rotation).tolist(),
                                 "cues": r.cues})
    out.write_text("".join(json.dumps(row) + "\n" for row in rows))


def run(args) -> int:
    from tqdm import tqdm

    out = Path(args.out)
    raw = out / "raw" / args.label
    raw.mkdir(parents=True, exist_ok=True)
    inputs = out / "raw" / "inputs.npz"
    if not inputs.is_file():
        print(f"preparing inputs: {prepare_inputs(inputs, args.data_root, args.limit)}", file=sys.stderr)
    settings = available_settings()
    if args.settings:
        chosen = {"reference"} | {name.strip() for name in args.settings.split(",")}
        settings = {name: s for name, s in settings.items() if name in chosen}
    jobs = [(mode, name, s, False) for mode in args.modes.split(",") for name, s in settings.items()]
    jobs += [(mode, f"shared kernels {k or 'native'}", (64, 0, "2", k), True)
             for mode in args.modes.split(",") for k in SHARED_KERNELS if args.shared
             if k is None or f"kernels {k}" in settings]  # --shared-focal under each kernel set
    env_base = dict(os.environ)
    if args.code:
        env_base["PYTHONPATH"] = os.pathsep.join([str(Path(args.code).resolve()), str(REPO)]
                                                 + [p for p in env_base.get("PYTHONPATH", "").split(os.pathsep) if p])
    timing = {}
    for mode, name, (batch, workers, threads, kernels), shared in tqdm(jobs, desc="settings", unit="setting"):
        target = raw / f"{mode}__{name.replace(' ', '_')}.jsonl"
        if target.is_file() and not args.again:
            continue
        env = dict(env_base, FR_THREADS=threads, **SETTING_ENV.get(name, {}))
        env.pop("ATEN_CPU_CAPABILITY", None)
        if kernels:
            env["ATEN_CPU_CAPABILITY"] = kernels
        command = [sys.executable, "-m", "fr_eval.protocols.reproducibility", "worker", "--inputs", str(inputs),
                   "--target", str(target), "--mode", mode, "--batch", str(batch), "--workers", str(workers)]
        if shared:
            command.append("--shared-group")
        start = time.perf_counter()
        # cwd: the checkout whose fr_torch runs (python -m puts the working folder first on sys.path)
        done = subprocess.run(command, env=env, capture_output=True, text=True, cwd=args.code or REPO)
        if done.returncode:
            print(f"{mode} / {name}: failed\n{done.stderr[-2000:]}", file=sys.stderr)
            continue
        timing[f"{mode} / {name}"] = round(time.perf_counter() - start, 1)
    (raw / "timing.json").write_text(json.dumps(timing, indent=1))
    return 0


def _rows(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def _angle_deg(a, b) -> float:
    from fr_torch.core.geometry.conventions import manhattan_frame_error_deg

    return manhattan_frame_error_deg(np.asarray(a), np.asarray(b))


def compare(reference: list[dict], rows: list[dict]) -> dict:
    """Differences of ``rows`` from ``reference`` (the same photos, in order), per dataset and over all."""
    out = {}
    for dataset in sorted({r["dataset"] for r in reference}) + ["all"]:
        pairs = [(a, b) for a, b in zip(reference, rows) if dataset in ("all", a["dataset"])]
        both = [(a, b) for a, b in pairs if a["ok"] and b["ok"]]
        rel = [abs(b["focal_px"] - a["focal_px"]) / a["focal_px"] for a, b in both]
        angle = [_angle_deg(a["rotation"], b["rotation"]) if a["rotation"] != b["rotation"] else 0.0 for a, b in both]
        out[dataset] = {
            "photos": len(pairs),
            "focal_differs": sum(r > 0 for r in rel) + sum(a["ok"] != b["ok"] for a, b in pairs),
            "cues_differ": sum(a["cues"] != b["cues"] for a, b in both),
            "max_rel_focal": max(rel, default=0.0),
            "max_rotation_deg": max(angle, default=0.0),
            "basin_changes": sum(r > BASIN_FOCAL or g > BASIN_ROTATION_DEG for r, g in zip(rel, angle))
            + sum(a["ok"] != b["ok"] for a, b in pairs),
            "reliable_flips": sum(a["reliable"] != b["reliable"] for a, b in pairs),
        }
    return out


def table(args) -> int:
    out = Path(args.out)
    lines, csv_rows = [], []
    for label in args.labels.split(","):
        raw = out / "raw" / label
        for mode in args.modes.split(","):
            ref_path = raw / f"{mode}__reference.jsonl"
            if not ref_path.is_file():
                continue
            reference = _rows(ref_path)
            lines += [f"\n**{label}, {'fR' if mode == 'fr' else 'Fast-fR'}** (against `reference`: batch 64, in "
                      f"process, FR_THREADS=2, the machine's kernel set, {native_kernels()})\n",
                      "| setting | dataset | photos | focal differs | max rel. focal diff. | max rotation diff. (deg) "
                      "| basin changes | reliable flips | cues differ |", "|---|---|---|---|---|---|---|---|---|"]
            for name in SETTINGS:
                path = raw / f"{mode}__{name.replace(' ', '_')}.jsonl"
                if name == "reference" or not path.is_file():
                    continue
                for dataset, c in compare(reference, _rows(path)).items():
                    lines.append(f"| {name} | {dataset} | {c['photos']} | {c['focal_differs']} | {c['max_rel_focal']:.1e} "
                                 f"| {c['max_rotation_deg']:.1e} | {c['basin_changes']} | {c['reliable_flips']} "
                                 f"| {c['cues_differ']} |")
                    csv_rows.append(dict(label=label, mode=mode, setting=name, dataset=dataset, **c))
            groups = {}
            for k in SHARED_KERNELS:
                path = raw / f"{mode}__shared_kernels_{k or 'native'}.jsonl"
                if path.is_file():
                    groups[k or "native"] = _rows(path)
            if groups:
                lines += ["", f"`--shared-focal`, groups of {GROUP_SIZE} YUD test photos, under each kernel set "
                          f"({', '.join(groups)}):", "",
                          "| group | focal (px) per kernel set | spread | error vs 674.9 px | principal point spread (px) |",
                          "|---|---|---|---|---|"]
                first = next(iter(groups.values()))
                for g in range(len(first)):
                    focal = [rows[g]["focal_px"] for rows in groups.values()]
                    pps = np.array([rows[g]["principal_point"] or [math.nan, math.nan] for rows in groups.values()])
                    spread_pp = float(np.nanmax(np.linalg.norm(pps - pps[:1], axis=1))) if len(pps) else math.nan
                    truth = first[g]["truth"]
                    lines.append(f"| {g + 1} | {' / '.join(f'{f:.2f}' for f in focal)} | {max(focal) / min(focal) - 1:.1e} "
                                 f"| {100 * abs(focal[0] / truth - 1):.2f} % | {spread_pp:.2f} |")
                    csv_rows.append(dict(label=label, mode=mode, setting="shared-focal", dataset=f"yud group {g + 1}",
                                         focal_spread=max(focal) / min(focal) - 1, pp_spread_px=spread_pp))
            timing = raw / "timing.json"
            if timing.is_file():
                seconds = {k: v for k, v in json.loads(timing.read_text()).items() if k.startswith(mode + " /")}
                if seconds:
                    lines += ["", "Seconds per setting (whole process, both datasets): "
                              + ", ".join(f"{k.split(' / ', 1)[1]} {v:g}" for k, v in seconds.items())]
    (out / "table.md").write_text("\n".join(lines).lstrip() + "\n")
    import pandas as pd

    pd.DataFrame(csv_rows).to_csv(out / "rows.csv", index=False)
    print((out / "table.md").read_text())
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fr_eval.protocols.reproducibility", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p_run = sub.add_parser("run", help="calibrate under every setting")
    p_run.add_argument("--out", default=str(DEFAULT_OUT))
    p_run.add_argument("--modes", default="fr,fast")
    p_run.add_argument("--label", default="current", help="name of this run's folder under raw/")
    p_run.add_argument("--code", default=None, help="another checkout's root to run (its fr_torch)")
    p_run.add_argument("--data-root", default=None)
    p_run.add_argument("--limit", type=int, default=None, help="photos per dataset (default all)")
    p_run.add_argument("--no-shared", dest="shared", action="store_false", help="skip the --shared-focal groups")
    p_run.add_argument("--settings", default=None, help="only these settings (comma-separated names of SETTINGS; the "
                                                        "reference always runs)")
    p_run.add_argument("--again", action="store_true", help="rerun settings whose rows exist")
    p_table = sub.add_parser("table", help="compare the settings with the reference")
    p_table.add_argument("--out", default=str(DEFAULT_OUT))
    p_table.add_argument("--modes", default="fr,fast")
    p_table.add_argument("--labels", default="current", help="runs to tabulate, comma-separated")
    p_worker = sub.add_parser("worker", help=argparse.SUPPRESS)
    p_worker.add_argument("--inputs", required=True)
    p_worker.add_argument("--target", required=True)
    p_worker.add_argument("--mode", required=True)
    p_worker.add_argument("--batch", type=int, default=64)
    p_worker.add_argument("--workers", type=int, default=0)
    p_worker.add_argument("--shared-group", action="store_true")
    args = parser.parse_args(argv)
    if args.command == "worker":
        worker(Path(args.inputs), Path(args.target), args.mode, args.batch, args.workers, args.shared_group)
        return 0
    return run(args) if args.command == "run" else table(args)


if __name__ == "__main__":
    sys.exit(main())
