"""Benchmarks: `python -m bench` runs them all, each writing its fragment in bench/results/, and
assembles docs/benchmarks.md from the fragments (`python -m bench assemble` only assembles)."""
