#!/usr/bin/env python
"""Regenerate ``fr_torch/data/mcmlsd/mcmlsd_params.npz`` from the MCMLSD authors' parameter files.

Reads (data only, no code) the HMM likelihood tables ``parameters/likelihood_model.mat`` and the
Elder-Zucker edge-detector filter taps ``ElderZuckerEdgeDetector/filters/*.ascii`` of the original
MCMLSD distribution and writes them to a small ``.npz`` inside the package, so that nothing under
the shared data folder is needed at run time.

Usage::

    python tools/make_mcmlsd_params.py [--src /work/shared/data/onlinefr/code/MCMLSD/code]
                                       [--out fr_torch/data/mcmlsd/mcmlsd_params.npz]

Stored arrays (float64):

* ``exist_edge_on/off`` (40,): P(an edge is observed at a sample | on / off state), per line-rank
  bin (lines ranked by Hough peak strength, 125 lines per bin; ``nexist_* = 1 - exist_*``).
* ``ang_dev_on/off`` (181,): P(angular deviation d | on / off) between the edge and the line,
  1-degree bins for d = -90 .. 90 degrees.
* ``length_prior`` (651,), ``lengths_on/off`` (161,): further tables of the original model
  (kept for reference; the detector uses the geometric length prior implied by its HMM).
* ``g{,1,2}{x,y}{05,1}``: 1-D Gaussian / 1st / 2nd derivative filter taps at scales 0.5 and 1 px.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import scipy.io

REPO = Path(__file__).resolve().parents[1]
DEFAULT_SRC = Path("/work/shared/data/onlinefr/code/MCMLSD/code")
DEFAULT_OUT = REPO / "fr_torch" / "data" / "mcmlsd" / "mcmlsd_params.npz"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--src", type=Path, default=DEFAULT_SRC)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args()

    mat = scipy.io.loadmat(str(args.src / "parameters" / "likelihood_model.mat"))
    arrays = {
        "exist_edge_on": mat["exist_edge_on"].ravel(),
        "exist_edge_off": mat["exist_edge_off"].ravel(),
        "ang_dev_on": mat["ang_dev_on_hist"].ravel(),
        "ang_dev_off": mat["ang_dev_off_hist"].ravel(),
        "length_prior": mat["length_prior"].ravel(),
        "lengths_on": mat["lengths_on"].ravel(),
        "lengths_off": mat["lengths_off"].ravel(),
    }
    for name in ("exist_edge_on", "exist_edge_off"):
        assert arrays[name].shape == (40,), (name, arrays[name].shape)
    for name in ("ang_dev_on", "ang_dev_off"):
        assert arrays[name].shape == (181,), (name, arrays[name].shape)
    nexist_on, nexist_off = mat["nexist_edge_on"].ravel(), mat["nexist_edge_off"].ravel()
    assert np.allclose(arrays["exist_edge_on"] + nexist_on, 1) and np.allclose(arrays["exist_edge_off"] + nexist_off, 1)

    for path in sorted((args.src / "ElderZuckerEdgeDetector" / "filters").glob("*.ascii")):
        taps = np.array(path.read_text().split(), dtype=np.float64)  # rows or columns: 1-D either way
        arrays[path.stem] = taps
    for needed in ("gx05", "g1x05", "g2x05", "gx1", "g1x1", "g2x1"):
        assert needed in arrays, f"missing filter {needed}"

    args.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(args.out, **{k: v.astype(np.float64) for k, v in arrays.items()})
    print(f"wrote {args.out} ({args.out.stat().st_size} bytes, {len(arrays)} arrays)")


if __name__ == "__main__":
    main()
