"""Benchmarks: `python -m bench` runs them all and assembles docs/benchmarks.md."""
