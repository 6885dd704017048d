"""Benchmarks of ddrt: `python -m bench.run` regenerates docs/BENCHMARKS.md (see bench/run.py)."""
