"""Benchmarks: each module prints a side-by-side table (ratios) from one run."""
