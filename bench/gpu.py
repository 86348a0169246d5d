"""The GPU beside this machine's CPU: the same work on each, side by side (ratios).

    python -m bench gpu [--parts chain,throughput,real_arm] [--budget 0.05] [--seeds 20]
                        [--updates 20] [--minutes 8] [chain overrides ...]

A fresh process first asks JAX for the GPU (``jax.devices("gpu")``, with the caller's
``JAX_PLATFORMS`` where set). Where there is none, one line says so, with JAX's backends, and
nothing else runs. Otherwise every measurement runs in fresh processes, once on the CPU
(``JAX_PLATFORMS=cpu``: one JAX device per core, as the pipeline runs there) and once on the GPU
(``JAX_PLATFORMS=cuda,cpu``: JAX's default backend is the GPU), one after the other. The tables
give each figure on both and the GPU's speed-up: CPU seconds / GPU seconds, or GPU steps/s / CPU
steps/s (above 1, the GPU is faster).

- ``chain``: the chain (default ``experiment=quick``) cold (a fresh output folder and an empty
  compilation cache) and warm (another fresh output folder, the cache the cold run filled):
  :func:`bench.chain.run_chain`'s runs; each stage's wall time, the trainings' compile and
  training seconds and the evaluation's headline figures (the same on both, to seed noise).
- ``throughput``: PPO and APG environment steps/s at ``--seeds`` seeds in the default learned
  environment (random model weights), ``--updates`` updates each:
  :func:`bench.ppo_throughput.measure`, the seeds split over the devices as the pipeline does.
- ``real_arm``: ``python -m pipeline stage=train_ppo experiment=real_arm agent=<policy>`` for each
  policy type the experiment evaluates (its 20 seeds), its budget (``agent.total_timesteps``,
  ``agent.recurrent_total_timesteps``) times ``--budget``. The models upstream (the recorded
  runs' model and its ensemble) are fitted once, by the first training, shrunk to
  ``model.num_steps=200`` (a training's speed does not depend on the weights); each training
  then recomputes only itself (``force=true``), with no compilation cache.

Sized to take at most about 8 minutes (``--minutes``) on a machine with one GPU. Each part has a
share of what is left of that budget when it starts (chain 45 %, throughput 15 %, real_arm
40 %; time a part leaves unused goes to the later ones): a process starts only within its part's
share, one still running at the end of the budget is stopped, and the output says which. Each
part prints its seconds; ``--parts`` and ``--minutes`` rerun what did not fit.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.chain import run_chain
from pipeline.config import PROJECT_ROOT, compose
from pipeline.infra.devices import usable_cores

PARTS = ("chain", "throughput", "real_arm")
CHAIN_OVERRIDES = ["experiment=quick"]
# the real-arm path's models, shrunk: fitted once, only so that the trainings have them
MODEL_SHRINK = ["model.num_steps=200", "model.eval_every=100", "model.checkpoint_every=100"]
MIN_LEFT_S = 20.0  # a process is not started with less time than this left to its part
# each part's share of the time budget (of what is left when it starts: time a part leaves
# unused goes to the later ones); 8 minutes: about 3.6, 1.2 and 3.2
SHARES = {"chain": 0.45, "throughput": 0.15, "real_arm": 0.40}
TRAINERS = ("ppo", "apg")
DASH = "—"

PROBE = """
import json
import jax

report = {"jax": jax.__version__, "default": None, "backends": {}, "gpu": None, "error": None}
for name in ("cpu", "cuda", "rocm"):
    try:
        found = jax.devices(name)
    except (RuntimeError, ValueError):
        continue
    report["backends"][name] = [d.device_kind for d in found]
try:
    gpus = jax.devices("gpu")
except (RuntimeError, ValueError) as error:
    message = " ".join(str(error).split())
    report["error"] = f"raised {type(error).__name__}: {message}"
else:
    if gpus:
        report["gpu"] = next((n for n in ("cuda", "rocm") if n in report["backends"]), "gpu")
    else:
        report["error"] = "returned no device"
report["default"] = jax.default_backend()
print(json.dumps(report))
"""


def probe() -> dict:
    """What a fresh JAX process finds: ``{"jax", "default", "backends": {name: [device kind,
    ...]}, "gpu": the GPU platform's name or None, "error"}``."""
    env = {**os.environ, "XLA_PYTHON_CLIENT_PREALLOCATE": "false", "PYTHONPATH": str(PROJECT_ROOT)}
    env.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")
    result = subprocess.run([sys.executable, "-c", PROBE], cwd=PROJECT_ROOT, env=env,
                            capture_output=True, text=True, timeout=300)
    if result.returncode != 0:
        last = (result.stderr.strip().splitlines() or ["(no message)"])[-1]
        return {"jax": None, "default": None, "backends": {}, "gpu": None,
                "error": f"was not reached: JAX did not start ({last})"}
    return json.loads(result.stdout.strip().splitlines()[-1])


def backends_line(report: dict) -> str:
    """``cpu (2 devices: cpu), default cpu; jax 0.9.2``."""
    parts = []
    for name, kinds in report["backends"].items():
        named = ", ".join(dict.fromkeys(kinds))
        parts.append(f"{name} ({len(kinds)} device{'s' * (len(kinds) != 1)}: {named})")
    line = ", ".join(parts) or "none"
    if report.get("default"):
        line += f", default {report['default']}"
    if report.get("jax"):
        line += f"; jax {report['jax']}"
    if os.environ.get("JAX_PLATFORMS"):
        line += f"; JAX_PLATFORMS={os.environ['JAX_PLATFORMS']} is set"
    return line


class Clock:
    """The run's time budget and the running part's share of it: a process starts only while
    its part has at least MIN_LEFT_S left, and is stopped at the end of the whole budget."""

    def __init__(self, minutes: float):
        self.end = time.monotonic() + 60.0 * minutes
        self.part_end = self.end

    def left(self) -> float:
        return self.end - time.monotonic()

    def start_part(self, share: float) -> None:
        self.part_end = time.monotonic() + share * max(0.0, self.left())

    def allows(self) -> bool:
        return min(self.part_end, self.end) - time.monotonic() >= MIN_LEFT_S


SKIPPED = {"error": "skipped: past its part's share of the time budget (--minutes)"}


def speedup(cpu: float | None, gpu: float | None, rate: bool = False) -> str:
    """The GPU's speed-up: CPU / GPU seconds, or GPU / CPU steps/s (``rate``)."""
    if not cpu or not gpu:
        return DASH
    return f"{(gpu / cpu if rate else cpu / gpu):.2f} x"


def _seconds(value: float | None) -> str:
    return DASH if value is None else f"{value:.1f}"


def _rate(value: float | None) -> str:
    return DASH if value is None else f"{value:.0f}"


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|---" * len(header) + "|"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def _errors(runs: dict[str, dict]) -> None:
    """Each failed or skipped run's message (a message said already: named once more only)."""
    said: dict[str, str] = {}
    for name, result in runs.items():
        if "error" in result:
            message = result["error"].strip()
            print(f"{name}: {message}" if message not in said else f"{name}: as {said[message]}")
            said.setdefault(message, name)


# --- chain ------------------------------------------------------------------------------------


def chain_part(sides: dict[str, str], overrides: list[str], tmp: Path, clock: Clock) -> None:
    """The chain cold and warm on each side (module doc)."""
    runs: dict[str, dict] = {}
    for phase in ("cold", "warm"):
        for index, (side, platforms) in enumerate(sides.items()):
            runs[f"{side} {phase}"] = (
                run_chain(PROJECT_ROOT, tmp / f"chain-{index}-{phase}", tmp / f"cache-{index}",
                          overrides, platforms, timeout=clock.left())
                if clock.allows() else SKIPPED)
    _errors(runs)
    cpu, gpu = sides
    ok = {n: r for n, r in runs.items() if "error" not in r}
    header = ["chain: " + " ".join(overrides)]
    for phase in ("cold", "warm"):
        header += [f"{cpu} {phase}", f"{gpu} {phase}", "GPU speed-up"]

    def row(label: str, value) -> list[str]:
        cells = [label]
        for phase in ("cold", "warm"):
            a, b = (value(ok[f"{s} {phase}"]) if f"{s} {phase}" in ok else None for s in sides)
            cells += [_seconds(a), _seconds(b), speedup(a, b)]
        return cells

    rows = [row("whole chain (wall s)", lambda r: r["wall_s"])]
    stages = list(dict.fromkeys(n for r in ok.values() for n in r["stages"]))
    rows += [row(f"{n} (s)", lambda r, n=n: r["stages"].get(n)) for n in stages]
    agents = list(dict.fromkeys(a for r in ok.values() for a in r["train"]))
    for agent in agents:
        rows.append(row(f"{agent}: compile s", lambda r, a=agent: r["train"].get(a, (None,))[0]))
        rows.append(row(f"{agent}: train s",
                        lambda r, a=agent: r["train"].get(a, (None, None))[1]))
    entries = list(dict.fromkeys(e for r in ok.values() for e in r.get("results", {})))
    for entry in entries:
        cells = [f"{entry}: median mm / ≤ 1 mm"]
        for phase in ("cold", "warm"):
            for side in sides:
                figures = ok.get(f"{side} {phase}", {}).get("results", {}).get(entry)
                cells.append(DASH if figures is None else "{:.3f} / {:.1%}".format(
                    figures["median_final_mm"], figures["success_1mm"]))
            cells.append(DASH)
        rows.append(cells)
    print(_table(header, rows))


# --- throughput -------------------------------------------------------------------------------


def worker(argv: list[str]) -> None:
    """``python -m bench.gpu --worker UPDATES SEEDS TRAINER ...``: each trainer's throughput on
    the default backend (the CPU: the pipeline's devices, one per core), one JSON line each."""
    updates, seeds, trainers = int(argv[0]), int(argv[1]), argv[2:]
    from pipeline.infra.devices import configure_cpu_devices

    configure_cpu_devices(None)  # before JAX starts: as the pipeline's entry point
    import jax

    from bench.ppo_throughput import measure

    for trainer in trainers:
        row = measure("default", updates, seeds, trainer)
        row["device"] = jax.devices()[0].device_kind
        print(json.dumps(row), flush=True)


def run_worker(platforms: str, updates: int, seeds: int, clock: Clock) -> dict[str, dict]:
    """Each trainer's throughput measured in one fresh process: ``{trainer: row or error}``."""
    if not clock.allows():
        return dict.fromkeys(TRAINERS, SKIPPED)
    env = {**os.environ, "JAX_PLATFORMS": platforms, "PYTHONPATH": str(PROJECT_ROOT)}
    env.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")
    for name in ("JAX_COMPILATION_CACHE_DIR", "SOROLEARN_COMPILE_CACHE"):  # compile cold
        env.pop(name, None)
    args = [sys.executable, "-m", "bench.gpu", "--worker", str(updates), str(seeds), *TRAINERS]
    try:
        result = subprocess.run(args, cwd=PROJECT_ROOT, env=env, capture_output=True, text=True,
                                timeout=clock.left())
        output, error = result.stdout, (result.stdout + result.stderr)[-2000:]
    except subprocess.TimeoutExpired as stopped:
        output = stopped.stdout.decode() if isinstance(stopped.stdout, bytes) else ""
        error = "stopped: the time budget ran out"
    rows = [json.loads(line) for line in output.splitlines() if line.startswith("{")]
    found = {row["trainer"]: row for row in rows}
    return {trainer: found.get(trainer, {"error": error}) for trainer in TRAINERS}


def throughput_part(sides: dict[str, str], updates: int, seeds: int, clock: Clock) -> None:
    """PPO and APG steps/s on each side (module doc)."""
    measured = {side: run_worker(platforms, updates, seeds, clock)
                for side, platforms in sides.items()}
    runs = {f"{trainer} {side}": measured[side][trainer]
            for trainer in TRAINERS for side in sides}
    _errors(runs)
    cpu, gpu = sides
    header = [f"{seeds} seeds, {updates} updates", f"{cpu} env steps/s", f"{gpu} env steps/s",
              "GPU speed-up", f"{cpu} compile s", f"{gpu} compile s", "devices (seeds split)"]
    rows = []
    for trainer in TRAINERS:
        a, b = runs[f"{trainer} {cpu}"], runs[f"{trainer} {gpu}"]
        rows.append([f"{trainer.upper()} (default env)",
                     DASH if "error" in a else f"{a['steps_per_s']:.0f}",
                     DASH if "error" in b else f"{b['steps_per_s']:.0f}",
                     speedup(a.get("steps_per_s"), b.get("steps_per_s"), rate=True),
                     _seconds(a.get("compile_s")), _seconds(b.get("compile_s")),
                     " / ".join(DASH if "error" in r else f"{r['devices']} {r['device']}"
                                for r in (a, b))])
    print(_table(header, rows))


# --- the real arm's trainings -----------------------------------------------------------------


def real_arm_part(sides: dict[str, str], budget: float, tmp: Path, clock: Clock) -> None:
    """Each policy type of experiment=real_arm trained on each side, ``budget`` of its steps."""
    cfg = compose("experiment=real_arm")
    agent = cfg.agent
    scaled = [f"agent.total_timesteps={int(budget * agent.total_timesteps)}"]
    if agent.recurrent_total_timesteps is not None:
        scaled.append(
            f"agent.recurrent_total_timesteps={int(budget * agent.recurrent_total_timesteps)}")
    policies = [str(p) for p in cfg.evaluation.policies]
    print(f"budget fraction {budget:g} of experiment=real_arm's ({agent.total_timesteps} steps a "
          f"seed, recurrent {agent.recurrent_total_timesteps}), {agent.num_seeds} seeds; models "
          f"upstream shrunk to {' '.join(MODEL_SHRINK)}, fitted once by the first training")
    runs: dict[str, dict] = {}
    for policy in policies:
        for side, platforms in sides.items():
            overrides = ["stage=train_ppo", "experiment=real_arm", f"agent={policy}", *scaled,
                         *MODEL_SHRINK, "force=true", "paths.compile_cache_dir=null"]
            runs[f"{policy} {side}"] = (
                run_chain(PROJECT_ROOT, tmp / "real_arm", None, overrides, platforms,
                          timeout=clock.left()) if clock.allows() else SKIPPED)
    _errors(runs)
    first = next((r for r in runs.values() if "error" not in r), None)
    if first is not None:
        upstream = sum(s for n, s in first["stages"].items() if not n.startswith("train_ppo"))
        print(f"models upstream (collect, align, fit_model and the ensemble, in the first "
              f"training's process): {upstream:.1f} s")
    cpu, gpu = sides
    header = [f"real arm, {agent.num_seeds} seeds", "steps a seed", f"{cpu} compile s", f"{gpu} compile s",
              f"{cpu} train s", f"{gpu} train s", f"{cpu} env steps/s", f"{gpu} env steps/s",
              "GPU speed-up", "final median mm (CPU / GPU)"]
    rows = []
    for policy in policies:
        a, b = (runs[f"{policy} {side}"].get("train_summaries", {}).get(policy, {})
                for side in sides)
        steps = a.get("timesteps_per_seed") or b.get("timesteps_per_seed")
        median = " / ".join(DASH if s.get("final_eval_median_distance_mm") is None
                            else f"{s['final_eval_median_distance_mm']:.3f}" for s in (a, b))
        rows.append([policy, DASH if steps is None else str(steps),
                     _seconds(a.get("compile_seconds")), _seconds(b.get("compile_seconds")),
                     _seconds(a.get("train_seconds")), _seconds(b.get("train_seconds")),
                     _rate(a.get("env_steps_per_second")),
                     _rate(b.get("env_steps_per_second")),
                     speedup(a.get("env_steps_per_second"), b.get("env_steps_per_second"),
                             rate=True), median])
    print(_table(header, rows))


# --- the run ----------------------------------------------------------------------------------


def compare(sides: dict[str, str], parts: list[str], args: argparse.Namespace) -> None:
    """Each part on both ``sides`` (``{name: JAX_PLATFORMS}``, the CPU's first)."""
    clock = Clock(args.minutes)
    with tempfile.TemporaryDirectory(prefix="bench-gpu-") as tmp:
        tmp = Path(tmp)
        for index, part in enumerate(parts):
            started = time.perf_counter()
            clock.start_part(SHARES[part] / sum(SHARES[p] for p in parts[index:]))
            print(f"\n--- {part} ---", flush=True)
            if part == "chain":
                chain_part(sides, args.overrides or CHAIN_OVERRIDES, tmp, clock)
            elif part == "throughput":
                throughput_part(sides, args.updates, args.seeds, clock)
            else:
                real_arm_part(sides, args.budget, tmp, clock)
            print(f"({part}: {time.perf_counter() - started:.0f} s)", flush=True)


def main(argv: list[str]) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", default=",".join(PARTS),
                        help=f"which parts, comma-separated (of {', '.join(PARTS)})")
    parser.add_argument("--budget", type=float, default=0.05,
                        help="the real-arm trainings' fraction of their budget")
    parser.add_argument("--seeds", type=int, default=20, help="seeds of the throughput part")
    parser.add_argument("--updates", type=int, default=20, help="updates of the throughput part")
    parser.add_argument("--minutes", type=float, default=8.0,
                        help="the time budget, shared by the parts (module doc)")
    parser.add_argument("overrides", nargs="*",
                        help="the chain's overrides (default: experiment=quick)")
    args = parser.parse_args(argv)
    parts = [p for p in args.parts.split(",") if p]
    unknown = sorted(set(parts) - set(PARTS))
    if unknown:
        raise SystemExit(f"unknown parts {unknown}; known: {list(PARTS)}")
    report = probe()
    if report["gpu"] is None:
        print(f"no GPU found: jax.devices('gpu') {report['error']}; JAX's backends: "
              f"{backends_line(report)}. Nothing run (the GPU's JAX: pip install -e \".[cuda]\")")
        return
    gpus = report["backends"][report["gpu"]]
    print(f"GPU: {len(gpus)} x {', '.join(dict.fromkeys(gpus))} ({report['gpu']}); CPU: "
          f"{usable_cores()} cores; JAX's backends: {backends_line(report)}")
    print("GPU speed-up: CPU seconds / GPU seconds, GPU steps/s / CPU steps/s (above 1: the "
          "GPU is faster)")
    compare({"CPU": "cpu", "GPU": f"{report['gpu']},cpu"}, parts, args)


if __name__ == "__main__":
    if sys.argv[1:2] == ["--worker"]:
        worker(sys.argv[2:])
    else:
        main(sys.argv[1:])
