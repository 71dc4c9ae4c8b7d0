"""The tensor engine: camera conventions, settings, the mixture likelihood, the two-stage search,
reliability cues and error model, and the estimator over padded segment batches.

No file I/O beyond the shipped configuration files, no argparse, no processes: everything here runs
on tensors (CPU or CUDA) and is what the layers above (:mod:`fr_torch.runtime`, :mod:`fr_torch.cli`)
call.
"""
