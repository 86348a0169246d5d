"""``python -m bench [name ...] [options]``: run the benchmarks (all but the optional ones by
default) and print their tables."""

from __future__ import annotations

import importlib
import sys

BENCHMARKS = {
    "chain": "bench.chain",
    "model_budget": "bench.model_budget",
    "model_cv": "bench.model_cv",
    "ppo_throughput": "bench.ppo_throughput",
    "control_latency": "bench.control_latency",
    "peers": "bench.peers",
    "ensemble_selection": "bench.ensemble_selection",
    "gru_kernel": "bench.gru_kernel",
    "time_to_controller": "bench.time_to_controller",
    "gpu": "bench.gpu",
}
# run only when named: peers needs the "peers" extra (torch, stable-baselines3); gpu compares a
# GPU with the CPU for minutes (where there is no GPU it says so and runs nothing)
OPTIONAL = {"peers", "gpu"}


def main(argv: list[str]) -> None:
    """``python -m bench [name ...] [-- | options of a single benchmark ...]``: the leading
    arguments that name benchmarks select them; what follows goes to each one's own ``main``."""
    count = next((i for i, a in enumerate(argv) if a not in BENCHMARKS), len(argv))
    names, rest = argv[:count], argv[count:]
    if rest and rest[0] == "--":
        rest = rest[1:]
    if not names:
        if rest and not rest[0].startswith("-"):
            raise SystemExit(f"unknown benchmark {rest[0]!r}; known: {sorted(BENCHMARKS)}")
        names = sorted(set(BENCHMARKS) - OPTIONAL)
    for name in names:
        print(f"\n=== {name} ===", flush=True)
        importlib.import_module(BENCHMARKS[name]).main(rest)


if __name__ == "__main__":
    main(sys.argv[1:])
