"""How fitted models answer small command steps and a held command, next to the recorded arm.

Near a goal a controller moves the valves by tenths of a kPa; the recorded walks change the
commands every period by much more. This script asks each model what the arm does there. From
the arm resting at each of ``--commands`` commands (drawn uniformly within one standard deviation
of the training runs' mean pressure per chamber, after 20 s at the runs' first command and 10 s
at the drawn one), chamber 0's command steps by each of ``--steps`` kPa and is held 8 s:

- ``moved at 8 s``: median / p90 distance [mm] from where the model rested before the step;
- ``drift``: how far the model moves between 5 s and 25 s after a 1 kPa step of one chamber,
  held (a resting arm that keeps moving).

A model whose answer is proportional to the step is what a soft arm near rest does; one that
moves millimetres for 0.06 kPa and hardly at all for 0.04 kPa has learned the size of a command
step as a switch. The recorded runs give the reference for the held command: each starts with
17 s at its first command, and ``--data`` prints how far the arm moved from 5 s to the end of it.

    python -m experiments.model_steps outputs/artifacts/fit_model/<key> [<key> ...] [--data]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from pipeline.dynamics.checkpoints import load_dynamics
from pipeline.dynamics.model import predict_sequence

MM_PER_M = 1000.0
PRELOAD_S, SETTLE_S, AFTER_S, DRIFT_FROM_S, DRIFT_TO_S = 20.0, 10.0, 8.0, 5.0, 25.0


def step_answers(params, preload: np.ndarray, start_pose: np.ndarray, commands: np.ndarray,
                 steps_kpa: list[float], model_hz: float) -> dict[str, np.ndarray]:
    """Per step size, the distance [mm] the model moved ``AFTER_S`` after the step from where it
    rested, one per command ``[C]``; and ``drift`` [C]: movement 5 → 25 s after a 1 kPa step."""
    n_pre, n_settle = round(PRELOAD_S * model_hz), round(SETTLE_S * model_hz)
    n_after, n_to = round(AFTER_S * model_hz), round(DRIFT_TO_S * model_hz)
    n_from = round(DRIFT_FROM_S * model_hz)

    def answer(command, delta, hold_steps):
        sequence = jnp.concatenate([jnp.broadcast_to(preload, (n_pre, 3)),
                                    jnp.broadcast_to(command, (n_settle, 3)),
                                    jnp.broadcast_to(command + delta, (hold_steps, 3))])
        return predict_sequence(params, sequence.astype(jnp.float32), start_pose)

    out = {}
    for size in steps_kpa:
        delta = jnp.asarray([size, 0.0, 0.0], jnp.float32)
        path = np.asarray(jax.vmap(lambda c, d=delta: answer(c, d, n_after))(commands))
        rest = path[:, n_pre + n_settle - 1]
        out[f"{size:g}"] = np.linalg.norm(path[:, -1] - rest, axis=-1) * MM_PER_M
    delta = jnp.asarray([1.0, 0.0, 0.0], jnp.float32)
    path = np.asarray(jax.vmap(lambda c: answer(c, delta, n_to))(commands))
    start = n_pre + n_settle
    out["drift"] = np.linalg.norm(path[:, start + n_to - 1] - path[:, start + n_from - 1],
                                  axis=-1) * MM_PER_M
    return out


def data_drift(runs) -> list[tuple[str, float, float]]:
    """Per recorded run: how long its first command was held [s] and how far the arm moved
    from 5 s to the end of that hold [mm] (NaN for a hold shorter than 5 s)."""
    rows = []
    for run in runs:
        changed = np.flatnonzero(np.any(np.diff(run.pressures_kpa, axis=0) != 0, axis=1))
        end = int(changed[0]) if len(changed) else len(run) - 1
        t = run.times_s - run.times_s[0]
        start = int(np.searchsorted(t, DRIFT_FROM_S))
        moved = (np.linalg.norm(run.positions_m[end] - run.positions_m[start]) * MM_PER_M
                 if start <= end else np.nan)
        rows.append((run.run_id, float(t[end]), float(moved)))
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("models", nargs="+", type=Path, help="fit_model artifact folders")
    parser.add_argument("--steps", type=float, nargs="+", default=[0.04, 0.06, 0.2, 1.0])
    parser.add_argument("--commands", type=int, default=64)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--data", action="store_true",
                        help="also the recorded runs' held first command (robot=sorolex_csv)")
    args = parser.parse_args(argv)

    from pipeline.studies import recorded_runs

    cfg, runs = recorded_runs("robot=sorolex_csv")
    if args.data:
        for run_id, held_s, moved in data_drift(runs):
            print(f"recorded {run_id}: first command held {held_s:.1f} s, moved {moved:.3f} mm "
                  f"from {DRIFT_FROM_S:g} s to its end")
    preload = np.asarray(runs[0].pressures_kpa[0], np.float32)
    start_pose = jnp.asarray(runs[0].positions_m[0], jnp.float32)
    print(f"moved {AFTER_S:g} s after a step of chamber 0 [mm], median / p90 over "
          f"{args.commands} resting commands; drift {DRIFT_FROM_S:g}-{DRIFT_TO_S:g} s after a "
          f"1 kPa step")
    for folder in args.models:
        params = load_dynamics(folder / "model.msgpack")
        mean = np.asarray(params.normalizer.pressure_mean)
        std = np.asarray(params.normalizer.pressure_std)
        rng = np.random.default_rng(args.seed)
        commands = jnp.asarray(rng.uniform(mean - std, mean + std, (args.commands, 3)),
                               jnp.float32)
        answers = step_answers(params, preload, start_pose, commands, args.steps,
                               float(cfg.dataset.model_hz))
        cells = [f"{name} kPa {np.median(v):.2f} / {np.quantile(v, 0.9):.2f}"
                 for name, v in answers.items() if name != "drift"]
        drift = answers["drift"]
        print(f"{folder.name}: " + ", ".join(cells)
              + f"; drift {np.median(drift):.2f} / {np.quantile(drift, 0.9):.2f}")


if __name__ == "__main__":
    main()
