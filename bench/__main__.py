"""``python -m bench [name ...]``: run the benchmarks (all by default) and print their tables."""

from __future__ import annotations

import importlib
import sys

BENCHMARKS = {
    "chain": "bench.chain",
    "model_budget": "bench.model_budget",
    "model_cv": "bench.model_cv",
    "ppo_throughput": "bench.ppo_throughput",
    "control_latency": "bench.control_latency",
    "ensemble_selection": "bench.ensemble_selection",
}


def main(argv: list[str]) -> None:
    names = [a for a in argv if not a.startswith("-")] or list(BENCHMARKS)
    unknown = sorted(set(names) - set(BENCHMARKS))
    if unknown:
        raise SystemExit(f"unknown benchmark(s) {unknown}; known: {sorted(BENCHMARKS)}")
    for name in names:
        print(f"\n=== {name} ===", flush=True)
        importlib.import_module(BENCHMARKS[name]).main([])


if __name__ == "__main__":
    main(sys.argv[1:])
