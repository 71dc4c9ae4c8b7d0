"""``fr bench``'s report: bench.md, bench.json and the figures from the measured rows, and the report
of a run that was cut short rebuilt from its ``bench.jsonl``."""
from __future__ import annotations

import json
import sys
from pathlib import Path

from fr_eval.bench import cold as bench_cold
from fr_eval.bench import detectors as bench_detectors
from fr_eval.bench import distortion as bench_distortion
from fr_eval.bench.contention import summary_lines
from fr_eval.bench.gpu import FLOPS_PER_DEVIATION, GPU_FP32_PEAK


def _figure(scale: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, key, xkey, xlabel in ((axes[0], "segments", "segments", "segments per image"),
                                  (axes[1], "grid", "hypotheses", "stage-1 hypotheses scored")):
        rows = scale[key]
        if not rows:
            continue
        x = [r[xkey] for r in rows]
        for stage in ("grid", "refine", "total"):
            ax.plot(x, [r[f"{stage}_ms"] for r in rows], marker="o", label=stage)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("ms per image (fast, batch 1)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    axes[1].set_title("k = " + ", ".join(str(r["k"]) for r in scale["grid"]))
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def grid_floor_ms(row: dict, ns: float, scored: bool = True) -> float:
    """The grid floor of an end-to-end row: G x N x 3 deviations at ``ns`` per atan2 + exp; G = the
    hypotheses stage 1 scored (``scored``; rows of older runs hold only k^4) or the whole k^4 grid."""
    count = row.get("grid_hypotheses_scored", row["grid_hypotheses"]) if scored else row["grid_hypotheses"]
    return count * row["segments"] * 3 * ns / 1e6


def latency_ratio(row: dict, ns: float, scored: bool = True) -> float:
    """An end-to-end row's total over its floor: wall ms / (decode + LSD + :func:`grid_floor_ms`), the
    issue's "ratio to the floor" (1 = nothing but decoding, detection and the grid's own arithmetic)."""
    return row["wall_ms"] / (row["decode_ms"] + row["lsd_ms"] + grid_floor_ms(row, ns, scored))


def _latency_lines(report: dict) -> list[str]:
    """bench.md's end-to-end latency table."""
    lines = ["## End-to-end latency per image (CPU, batch 1, ms)", "",
              "| image | mode | segments | decode+LSD | grid | refine | cues | total | floor: decode | floor: LSD "
              "| grid floor: scored | grid floor: k^4 | total ÷ floor (scored; k^4) |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    ns = report["transcendental_ns"]
    for r in report["end_to_end"]:
        lines.append(f"| {r['image']} | {r['mode']} | {r['segments']} | {r['detect_ms']:.1f} | {r['grid_ms']:.1f} | "
                     f"{r['refine_ms']:.1f} | {r['cues_ms']:.1f} | **{r['wall_ms']:.1f}** | {r['decode_ms']:.1f} | "
                     f"{r['lsd_ms']:.1f} | {grid_floor_ms(r, ns):.1f} | {grid_floor_ms(r, ns, scored=False):.1f} | "
                     f"{latency_ratio(r, ns):.2f} ({latency_ratio(r, ns, scored=False):.2f}) |")
    lines += ["", "Grid floor = G x N x 3 deviations x (atan2 + exp ns/element measured in cache: "
              f"{ns:.2f} ns); G = the hypotheses stage 1 scored (coarse to fine: 768 per photo at the "
              "defaults) or the whole k^4 grid (4,096); the grid column also holds the focal sweep and the "
              "lattice passes.", ""]
    return lines


def _markdown(report: dict) -> str:
    m = report["machine"]
    lines = ["# fR speed benchmark", "",
             f"Machine: {m['cpu']}, {m['cores']} cores, torch {m['torch']}, {m['threads']} threads, "
             f"device {m['device']}" + (f" ({m['gpu']})" if "gpu" in m else "")
             + (f", MKL branch {m['mkl_branch']}" if m.get("mkl_branch") else "")
             + (f", load average {m.get('load_average')}" if m.get("load_average") else "") + ".",
             f"Command: `{report['command']}`; medians over {report['repeats']} runs after a warm-up "
             f"(GPU rows and large batches fewer: each row's `repeats` in bench.json).", ""]
    if report.get("from_jsonl"):
        lines += [f"Rebuilt from the rows of `{report['from_jsonl']}` (`fr bench --from-jsonl`): what that run "
                  "had measured when it ended.", ""]
    if report["end_to_end"]:
        lines += _latency_lines(report)
    lines += bench_cold.markdown_lines(report.get("cold_start", []))
    lines += bench_detectors.markdown_lines(report)
    lines += bench_distortion.markdown_lines(report.get("distortion", []))
    lines += ["## Throughput given segments (grid + refinement + cues)", "",
              "| device | mode | batch | segments | images/s | ms/image | peak memory (MB) |",
              "|---|---|---|---|---|---|---|"]
    mem = {(r["batch"], r["device"]): r for r in report["memory"] if r.get("ok")}
    for r in report["throughput"]:
        peak = r.get("peak_memory_mb")
        if peak is None and r.get("mode", "fast") == "fast" and (r["batch"], r["device"]) in mem:
            peak = mem[(r["batch"], r["device"])]["peak_increase_mb"]
        mode = r.get("mode", "fast") + ("" if r.get("reliability", True) else ", reliability off")
        lines.append(f"| {r['device']} | {mode} | {r['batch']} | {r['segments']} | "
                     f"{r['images_per_s']:.1f} | {r['ms_per_image']:.2f} | {'' if peak is None else f'{peak:.0f}'} |")
    if report["memory"]:
        lines += ["", "## Peak memory (fresh subprocess per setting; CPU: peak RSS increase over the inputs)", "",
                  "| device | mode | batch | segments | k | peak increase (MB) | peak RSS (MB) | seconds | ok |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for r in report["memory"]:
            if "peak_increase_mb" in r:
                lines.append(f"| {r['device']} | {r['mode']} | {r['batch']} | {r['segments']} | {r['k']} | "
                             f"{r['peak_increase_mb']:.0f} | {r['peak_rss_mb']:.0f} | {r['seconds']:.1f} | {r['ok']} |")
            else:
                lines.append(f"| {r['device']} | {r['mode']} | {r['batch']} | {r['segments']} | {r['k']} | - | - | - | "
                             f"FAILED: {r.get('error')} |")
    if report["scaling"]:
        lines += ["", "## Scaling (fast, batch 1, CPU, ms per image)", "", "| segments | grid | refine | cues | total |",
                  "|---|---|---|---|---|"]
        for r in report["scaling"]["segments"]:
            lines.append(f"| {r['segments']} | {r['grid_ms']:.1f} | {r['refine_ms']:.1f} | {r['cues_ms']:.1f} | {r['total_ms']:.1f} |")
        lines += ["", "| k | hypotheses scored | grid | refine | total |", "|---|---|---|---|---|"]
        for r in report["scaling"]["grid"]:
            lines.append(f"| {r['k']} | {r['hypotheses']} | {r['grid_ms']:.1f} | {r['refine_ms']:.1f} | {r['total_ms']:.1f} |")
        lines += ["", "![scaling](scaling.png)", ""]
    if report.get("parallel"):
        lines += ["## CPU parallelism (given segments, images/s)", "",
                  "T intra-op threads in one process vs W single-threaded worker processes "
                  "(`fr_torch.runtime.pipeline.calibrate_segments_sharded`); batch "
                  f"{report['parallel'][0]['batch']} x {report['parallel'][0]['segments']} segments.", "",
                  "| mode | kind | count | images/s | ms/image | speed-up vs 1 |", "|---|---|---|---|---|---|"]
        base = {(r["mode"], r["kind"]): r["images_per_s"] for r in report["parallel"] if r["count"] == 1}
        for r in report["parallel"]:
            ref = base.get((r["mode"], r["kind"]))
            speedup = f"{r['images_per_s'] / ref:.2f}x" if ref else ""
            lines.append(f"| {r['mode']} | {r['kind']} | {r['count']} | {r['images_per_s']:.1f} | {r['ms_per_image']:.2f} | "
                         f"{speedup} |")
        lines.append("")
    if report.get("outside_search"):
        lines += ["## Work outside the search (per image)", "",
                  "`calibrate_segments` on a large batch with a minimal search (k = 2, one start, no sweep or passes, one "
                  "step): input checks, segment filter, batching, records, checks, cues (the `focal_prior_share` "
                  "cue scores an 81-point lattice per image: device work, like the minimal search), reliability "
                  "predictions. 1000 / ms bounds the images/s of this device.", "",
                  "| device | batch | segments | ms/image | ceiling (images/s) |", "|---|---|---|---|---|"]
        lines += [f"| {r['device']} | {r['batch']} | {r['segments']} | {r['ms_per_image']:.3f} | "
                  f"{r['ceiling_images_per_s']:.0f} |" for r in report["outside_search"]]
        lines.append("")
    if report.get("grid_kernel"):
        lines += ["## Grid kernel alone (stage 1: 8^4 hypotheses, `score_grid`)", "",
                  f"Deviations = B x G x N x 3 (nominal). Fraction of FP32 peak: {FLOPS_PER_DEVIATION} FLOPs per "
                  "deviation (a convention: s, t, atan2, exp, mixture) against the GPU's data-sheet FP32 peak "
                  f"({', '.join(f'{k} {v / 1e12:.1f} TFLOP/s' for k, v in GPU_FP32_PEAK.items())}).", "",
                  "| device | batch | segments | hypotheses | ms | images/s | deviations/s | fraction of FP32 peak |",
                  "|---|---|---|---|---|---|---|---|"]
        for r in report["grid_kernel"]:
            fraction = r.get("fraction_of_fp32_peak")
            lines.append(f"| {r['device']} | {r['batch']} | {r['segments']} | {r['hypotheses']} | "
                         f"{1000 * r['seconds']:.1f} | {r['images_per_s']:.0f} | {r['deviations_per_s']:.3g} | "
                         f"{'' if fraction is None else f'{100 * fraction:.1f} %'} |")
        lines.append("")
    for p in report.get("profiles", []):
        lines += [f"## Where the time goes: {p['device']} {p['mode']}, batch {p['batch']} (torch profiler, "
                  f"full table in `{p['file']}`)", "", "| op | self ms | share | calls |", "|---|---|---|---|"]
        lines += [f"| `{_short_op(o['op'])}` | {o['self_ms']:.1f} | {100 * o['share']:.0f} % | {o['calls']} |"
                  for o in p["top_ops"]]
        lines.append("")
    if report.get("contention"):
        lines += ["## Under contention (CPU, seconds per photo, one photo per call)", "",
                  "Fresh processes with the commands' thread policy (`FR_THREADS` = "
                  f"{m.get('fr_threads', 'auto')}): idle; beside a busy neighbour (a pure-Python spin loop in a "
                  "subprocess keeping one core busy); 2 such processes side by side (photos/s of the 2 together "
                  "over one alone's). `segments` = given segments, `images` = decode + LSD + search. "
                  "docs/cpu-threads.md.", ""]
        lines += summary_lines(report["contention"], (2,)) + [""]
    if report.get("skipped"):
        lines += [f"Skipped (time budget {report['budget_s']:.0f} s): " + ", ".join(report["skipped"]) + ".", ""]
    return "\n".join(lines)


def _short_op(name: str, limit: int = 100) -> str:
    """A profiler op name short enough for a table cell: a CUDA kernel's C++ signature is cut to its
    name and template arguments without ``at::native::``, then to ``limit`` characters (the full
    names are in the profile file)."""
    if name.startswith("void "):
        name = name[5:]
    name = name.split(">(", 1)[0].replace("at::native::", "") + (">" if ">(" in name else "")
    return name if len(name) <= limit else name[:limit - 1] + "…"


def write_report(report: dict, out: Path) -> None:
    """bench.json, bench.md and the figures of ``report`` in ``out``: scaling.png (time against
    segments and grid size) when it has the scaling rows, throughput.png when it has throughput rows."""
    written = [out / "bench.md", out / "bench.json"]
    markdown = _markdown(report)
    (out / "bench.json").write_text(json.dumps(report, indent=1))
    (out / "bench.md").write_text(markdown)
    if report.get("scaling"):
        _figure(report["scaling"], out / "scaling.png")
        written.append(out / "scaling.png")
    if report.get("throughput"):
        _throughput_figure(report["throughput"], out / "throughput.png")
        written.append(out / "throughput.png")
    print(markdown)
    print(f"fr bench: wrote {', '.join(map(str, written))}", file=sys.stderr)


def report_from_jsonl(path: Path) -> dict:
    """The report of an earlier run rebuilt from its ``bench.jsonl`` rows (what was measured before
    it ended; the profiles without their top-op tables, which only the full report holds)."""
    rows = [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]
    by = {}
    for row in rows:
        by.setdefault(row.pop("section"), []).append(row)
    machine = (by.get("machine") or [{}])[0]
    scale = {"segments": [r for r in by.get("scaling", []) if "k" not in r],
             "grid": [r for r in by.get("scaling", []) if "k" in r]}
    return {"machine": {k: v for k, v in machine.items() if k not in ("command", "repeats", "budget_s")} or
            {"cpu": "not recorded", "cores": "?", "torch": "?", "threads": "?", "device": "?"},
            "command": machine.get("command", f"(rows of {path})"), "quick": False,
            "repeats": machine.get("repeats", "?"),
            "transcendental_ns": (by.get("transcendental") or [{"ns_per_element": float("nan")}])[0]["ns_per_element"],
            "end_to_end": by.get("end_to_end", []), "cold_start": by.get("cold", []),
            "throughput": by.get("throughput", []),
            "memory": by.get("memory", []), "scaling": scale if scale["segments"] or scale["grid"] else {},
            "parallel": by.get("parallel", []), "outside_search": by.get("outside_search", []),
            "grid_kernel": by.get("grid_kernel", []), "detectors": by.get("detectors", []), "contention": by.get("contention", []),
            "distortion": by.get("distortion", []),
            "device_end_to_end": by.get("device_end_to_end", []), "profiles": [], "skipped": [],
            "budget_s": machine.get("budget_s", 0.0), "sections": [], "from_jsonl": str(path)}


def _throughput_figure(rows: list[dict], path: Path) -> None:
    """Images/s against batch size (log-log), one line per device, mode, search and reliability."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lines: dict = {}
    for r in rows:
        key = (r["device"], r.get("mode", "fast"), r.get("search", "eager"), r.get("reliability", True))
        lines.setdefault(key, []).append((r["batch"], r["images_per_s"]))
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for (device, mode, search, reliability), points in sorted(lines.items()):
        points.sort()
        label = f"{device} {mode} {search}" + ("" if reliability else ", reliability off")
        ax.plot([b for b, _ in points], [v for _, v in points], marker="o",
                linestyle="-" if search == "eager" else "--", label=label)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("batch (images searched together)")
    ax.set_ylabel("images/s given 300 segments per image")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
