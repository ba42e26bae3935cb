"""gpocc's benchmark suite: ``make bench`` runs ``python -m bench.run_bench``, which writes
docs/benchmarks.md. ``bench/experiment.py`` (``make experiment``) is the accuracy suite."""
