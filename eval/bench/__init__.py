"""``fr bench`` and the speed measurements beside it: one module per section of the benchmark
(:mod:`fr_eval.bench.command` runs them and writes the report), and whole-process benchmarks
(:mod:`fr_eval.bench.folder`, :mod:`fr_eval.bench.contention`)."""
