"""Operators per image: how many torch operators one ``calibrate_segments`` call runs, divided by the
batch size (the CPU proxy for a GPU's kernel launches).

``python tools/op_count.py [--modes fast,fr] [--batches 64,256] [--segments 300]``: synthetic
640x480 scenes (``fr_eval.bench.timing.scene_segments``), reliability stage on (the defaults), one
thread, after one warm-up call; counts the top-level operator events ``torch.profiler`` records
(nested ``aten::`` calls inside a composite op are not counted twice) and prints a Markdown table.
``--chunking device`` lifts the CPU's cache-sized chunks (``fr_torch.core.search.grid.CPU_CHUNK_ELEMENTS``,
``CPU_REFINE_ELEMENTS``; the cues' ``SEGMENT_CHUNK_IMAGES``, ``LATTICE_FIT_ELEMENTS`` and
``PROFILE_CHUNK_IMAGES`` set to a GPU's answer) so the batch is cut as on a GPU
(``SearchConfig.max_chunk_elements``): the count is then the proxy for a GPU's kernel launches (with :mod:`fr_torch.core.exact_math`'s functions
as torch's own, as on a GPU); ``cpu`` (default) counts what a CPU runs.
Run it with ``PYTHONPATH=<another checkout>`` to count another version of the library.
"""
from __future__ import annotations

import argparse

import torch


def _device_like(batch: int, n_segments: int):
    """(features-like, max_chunk_elements) giving :func:`fr_torch.core.reliability.cues.segment_chunk_images`'s
    answer on a GPU for ``batch`` images of ``n_segments`` at the configuration's default."""
    from types import SimpleNamespace

    from fr_torch.core.settings.config import SearchConfig
    weight = SimpleNamespace(device=torch.device("cuda"), shape=(batch, n_segments))
    return SimpleNamespace(weight=weight), SearchConfig.max_chunk_elements


def count_operators(mode: str, batch: int, n_segments: int, chunking: str = "cpu") -> tuple[int, int]:
    """(top-level operator events, all operator events) of one batch of ``batch`` scenes."""
    from torch.profiler import ProfilerActivity, profile

    import fr_torch.core.search.grid as grid
    import fr_torch.core.search.refine as refine
    from fr_eval.bench.timing import bench_estimator, scene_segments

    if chunking == "device":
        grid.CPU_CHUNK_ELEMENTS = refine.CPU_REFINE_ELEMENTS = 1 << 40
        import fr_torch.core.reliability.cues as cues  # the cues' lattice terms: a GPU's chunks
        like, elements = _device_like(batch, n_segments)
        cues.SEGMENT_CHUNK_IMAGES = cues.segment_chunk_images(like, elements)
        cues.LATTICE_FIT_ELEMENTS = 1 << 40
        cues.PROFILE_CHUNK_IMAGES = cues.profile_chunk_images(like, len(cues.PROFILE_FOCAL_RATIOS), elements)
        # on a GPU fr_torch.core.exact_math's functions are torch's own, one operator each (on a CPU
        # without the compiled loops they are written out in some thirty)
        import fr_torch.core.exact_math as exact_math
        exact_math._native = lambda x: True

    est = bench_estimator(mode, "cpu")
    pool = [scene_segments(n_segments, seed=i) for i in range(8)]
    segs, sizes = [pool[i % len(pool)] for i in range(batch)], [(640, 480)] * batch
    est.calibrate_segments(segs[:2], sizes[:2])
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        est.calibrate_segments(segs, sizes)
    events = [e for e in prof.events() if e.name.startswith("aten::")]
    ids = {e.id for e in events}
    top = [e for e in events if e.cpu_parent is None or e.cpu_parent.id not in ids]
    return len(top), len(events)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--modes", default="fast,fr")
    parser.add_argument("--batches", default="64,256")
    parser.add_argument("--segments", type=int, default=300)
    parser.add_argument("--chunking", choices=("cpu", "device"), default="cpu")
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(f"chunking: {args.chunking}\n")
    print("| mode | batch | operators per batch (top level) | per image | all aten events per image |")
    print("| --- | --- | --- | --- | --- |")
    for mode in args.modes.split(","):
        for batch in map(int, args.batches.split(",")):
            top, every = count_operators(mode, batch, args.segments, args.chunking)
            print(f"| {mode} | {batch} | {top:,} | {top / batch:,.1f} | {every / batch:,.1f} |", flush=True)


if __name__ == "__main__":
    main()
