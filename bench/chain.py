"""The default chain end to end, cold and warm: what a user waits for.

Runs ``python -m pipeline`` (or the given overrides) in fresh processes into fresh output
folders: first with an empty compilation cache (cold), then again into another fresh output
folder with the cache the first run filled (warm). Prints each stage's wall time and, for
train_ppo, its compile and training seconds, side by side, and the evaluation's headline
figures (median final distance and success within 1 mm, per plant and controller).
``--ref COMMIT`` adds the same chain run from that commit (a temporary git worktree, with its
own cold runs), where it still runs.

    python -m bench chain [--ref a8a1940] [overrides ...]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from pipeline.config import PROJECT_ROOT

STAGE_LINE = re.compile(r"stage (\S+(?: \([^)]*\))?) done in ([\d.]+) s")
TRAIN_LINE = re.compile(r"train_ppo: (\{.*\})")
HEADLINE_LINE = re.compile(r"evaluate: (\{.*\})")


def run_chain(root: Path, output: Path, cache: Path | None, overrides: list[str],
              platforms: str = "cpu", timeout: float | None = None) -> dict:
    """Run the chain from checkout ``root`` with ``JAX_PLATFORMS=platforms`` (at most
    ``timeout`` seconds); return wall time, stage times and train timings (``train_summaries``:
    each training's whole summary line)."""
    env = {**os.environ, "PYTHONPATH": str(root), "JAX_PLATFORMS": platforms}
    env.pop("SOROLEARN_COMPILE_CACHE", None)
    args = [sys.executable, "-m", "pipeline", f"paths.output_dir={output}", *overrides]
    if cache is not None:
        args.append(f"paths.compile_cache_dir={cache}")
    started = time.perf_counter()
    try:
        result = subprocess.run(args, cwd=root, env=env, capture_output=True, text=True,
                                timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"wall_s": time.perf_counter() - started,
                "error": f"stopped after {timeout:.0f} s (the time left to it)"}
    wall = time.perf_counter() - started
    log = result.stdout + result.stderr
    if result.returncode != 0:
        return {"wall_s": wall, "error": log[-2000:]}
    stages = {name: float(s) for name, s in STAGE_LINE.findall(log)}
    trainings = [json.loads(m) for m in TRAIN_LINE.findall(log)]
    headlines = [json.loads(m) for m in HEADLINE_LINE.findall(log)]
    return {"wall_s": wall, "stages": stages,
            "train": {t["agent"]: (t["compile_seconds"], t["train_seconds"]) for t in trainings},
            "train_summaries": {t["agent"]: t for t in trainings},
            "results": headlines[-1] if headlines else {}}


def table(runs: dict[str, dict]) -> str:
    names = list(dict.fromkeys(n for r in runs.values() for n in r.get("stages", {})))
    lines = ["| | " + " | ".join(runs) + " |", "|---" * (len(runs) + 1) + "|"]
    lines.append("| whole chain (wall s) | " + " | ".join(f"{r['wall_s']:.1f}" for r in
                                                         runs.values()) + " |")
    for name in names:
        lines.append(f"| {name} | " + " | ".join(
            f"{r['stages'][name]:.1f}" if name in r.get("stages", {}) else "—"
            for r in runs.values()) + " |")
    agents = list(dict.fromkeys(a for r in runs.values() for a in r.get("train", {})))
    for agent in agents:
        lines.append(f"| {agent}: compile / train s | " + " | ".join(
            "{:.1f} / {:.1f}".format(*r["train"][agent]) if agent in r.get("train", {})
            else "—" for r in runs.values()) + " |")
    # the report's headline: a faster chain must give the same figures (within seed noise)
    entries = list(dict.fromkeys(e for r in runs.values() for e in r.get("results", {})))
    for entry in entries:
        lines.append(f"| {entry}: median mm / ≤ 1 mm | " + " | ".join(
            "{:.3f} / {:.1%}".format(r["results"][entry]["median_final_mm"],
                                     r["results"][entry]["success_1mm"])
            if entry in r.get("results", {}) else "—" for r in runs.values()) + " |")
    return "\n".join(lines)


def main(argv: list[str]) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ref", help="also run the chain of this commit (cold)")
    parser.add_argument("overrides", nargs="*")
    args = parser.parse_args(argv)
    runs = {}
    with tempfile.TemporaryDirectory(prefix="bench-chain-") as tmp:
        tmp = Path(tmp)
        cache = tmp / "cache"
        runs["cold"] = run_chain(PROJECT_ROOT, tmp / "cold", cache, args.overrides)
        runs["warm (cache kept)"] = run_chain(PROJECT_ROOT, tmp / "warm", cache, args.overrides)
        if args.ref:
            checkout = tmp / "ref"
            subprocess.run(["git", "worktree", "add", "--detach", str(checkout), args.ref],
                           cwd=PROJECT_ROOT, check=True, capture_output=True)
            try:
                runs[f"{args.ref} (cold)"] = run_chain(checkout, tmp / "ref-out", None,
                                                      args.overrides)
            finally:
                subprocess.run(["git", "worktree", "remove", "--force", str(checkout)],
                               cwd=PROJECT_ROOT, capture_output=True)
    for name, result in runs.items():
        if "error" in result:
            print(f"{name}: the chain failed:\n{result['error']}")
    print(f"cores: {os.cpu_count()}; overrides: {' '.join(args.overrides) or '(default chain)'}")
    print(table({k: v for k, v in runs.items() if "error" not in v}))


if __name__ == "__main__":
    main(sys.argv[1:])
