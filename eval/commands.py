"""The ``fr`` subcommands that need the evaluation harness.

Each is registered in ``pyproject.toml`` under the ``fr_torch.commands`` entry-point group as
``name = "fr_eval.commands:CONSTANT"``; a value is ``(module, one-line help)``, where the module
provides ``add_arguments(parser)`` and ``run(args) -> int``.  This module stays light: ``fr`` reads
it to list the commands and imports the command's module only when it runs.
"""
EVAL = ("fr_eval.protocols.eval_command", "evaluate methods on a dataset (camera or vanishing-point task): tables "
        "and figures")
FIT_LIKELIHOOD = ("fr_eval.protocols.fit_likelihood", "fit the deviation-measure likelihoods from labelled data")
MAKE_DATASET = ("fr_eval.datasets.make_dataset", "cut planar views with known camera from panoramas")
TRAIN_RELIABILITY = ("fr_eval.protocols.reliability_train", "train the error predictor (reliability model)")
BENCH = ("fr_eval.bench.command", "speed benchmark (latency, throughput, memory)")

# name -> (module, help), in the order of pyproject.toml (used by ``python -m fr_eval``).
COMMANDS = {"eval": EVAL, "fit-likelihood": FIT_LIKELIHOOD, "make-dataset": MAKE_DATASET,
            "train-reliability": TRAIN_RELIABILITY, "bench": BENCH}
