"""How closely any command sequence at the control rate follows a reference on a plant.

For every tracking episode of an evaluation (its plants, start states and references, built as
``stage=evaluate`` builds them: :func:`pipeline.evaluation.tracking.run_tracking`, and in the
cross-model protocol each group's own model and the other group's), the command sequence that
follows the reference closest, found by gradient descent through the plant over the whole
episode: it knows the plant exactly and the reference ahead, so no controller at the same rate
does better on that plant, up to the search (it is local: what it finds is achievable, so its
RMSE is an upper bound of the best possible). One command per control period, held as the
environment holds it, projected onto the safe set; scored as the evaluation scores a path
(:func:`pipeline.evaluation.tracking.tracking_metrics`, after the settling time).

Holding the preload through the same code reproduces the evaluation's ``preload`` rows (checked,
to 0.01 mm), so the plants, starts and references are the evaluation's::

    python -m experiments.tracking_oracle experiment=real_arm_tracking evaluation.reaching=false \\
        agent.num_seeds=4 evaluation.cross_model_seeds=4 'evaluation.tracking_baselines=[preload]'

The plants' models must exist (run the evaluation, or ``stage=fit_model``, with the same
overrides first). Rows go to ``--out`` (JSON lines).
"""

from __future__ import annotations

import argparse
import functools
import json
import logging
import math
import shlex
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

DEFAULT_OUT = "outputs/tracking_oracle/oracle.jsonl"
START_KPA = 0.5

log = logging.getLogger(__name__)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("overrides", nargs="*", help="Hydra overrides of the evaluate stage")
    parser.add_argument("--iterations", type=int, default=400, help="Adam steps")
    parser.add_argument("--lr", type=float, default=0.1, help="Adam's step size [kPa]")
    parser.add_argument("--protocols", default="",
                        help="comma-separated: 'all runs', 'A->B', 'B->A' (default: every one)")
    parser.add_argument("--out", default=DEFAULT_OUT)
    parser.add_argument("--report", action="store_true", help="print the table of --out")
    return parser.parse_args(argv)


def optimal_commands(env: Any, env_params: Any, start_carries: Any, preload: Any,
                     targets: Any, settle: int, iterations: int, lr: float):
    """``(commands [E, T, 3] kPa, positions [E, T, 3] m, preload positions [E, T, 3] m)``,
    row k of the positions after period k + 1: per episode the commands nearest ``targets
    [E, T + 1, 3]`` m (row k: after k periods) over the rows ``settle ... T``, as the evaluation
    scores them (mean squared distance, ``iterations`` Adam steps of ``lr`` kPa from the
    preload plus :data:`START_KPA`), and the positions holding the preload gives."""
    import jax
    import jax.numpy as jnp
    import optax

    from pipeline.arm.safety import project
    from pipeline.rl.envs.plants import hold

    steps = targets.shape[1] - 1

    def path(carry, commands):
        def period(carry, command):
            carry, positions = hold(env.plant, env_params.plant, carry,
                                    project(command, env_params.safe_set),
                                    int(env.steps_per_action))
            return carry, positions[-1]

        return jax.lax.scan(period, carry, commands)[1]

    def loss(commands, carry, target):  # the positions after periods settle ... T
        first = max(settle, 1)
        error = path(carry, commands)[first - 1:] - target[first:]
        return jnp.mean(jnp.sum(jnp.square(error), axis=-1))

    optimizer = optax.adam(lr)

    def solve(carry, target):
        # from the preload raised by START_KPA a valve: at the settled preload itself the
        # twin's hysteresis play passes no gradient
        commands = jnp.broadcast_to(preload + START_KPA, (steps, 3))

        def update(state, _):
            commands, opt_state = state
            value, grad = jax.value_and_grad(loss)(commands, carry, target)
            change, opt_state = optimizer.update(grad, opt_state)
            return (optax.apply_updates(commands, change), opt_state), value

        (commands, _), _ = jax.lax.scan(update, (commands, optimizer.init(commands)), None,
                                        length=iterations)
        return project(commands, env_params.safe_set), path(carry, commands)

    commands, positions = jax.vmap(solve)(start_carries, targets)
    held = jax.vmap(lambda carry: path(carry, jnp.broadcast_to(preload, (steps, 3))))(
        start_carries)
    return commands, positions, held


@functools.cache
def jitted_optimal_commands():
    import jax

    return jax.jit(optimal_commands, static_argnames=("env", "settle", "iterations"))


def plant_sets(overrides: list[str]) -> tuple[Any, dict[str, tuple[Any, Any]]]:
    """The evaluate stage's config and, by protocol, its tracking settings (with the measured
    paths a replayed reference follows: those of the protocol's own runs) and its plants:
    ``"all runs"`` (the learned env of the config, its twins and other models) and each
    cross-model direction (``own``, ``cross``), built as ``stage=evaluate`` builds them."""
    import jax

    from pipeline import chain, keys
    from pipeline.arm.twins import twin_physics
    from pipeline.config import compose
    from pipeline.dynamics.checkpoints import load_dynamics
    from pipeline.evaluation.closed_loop import _plants
    from pipeline.evaluation.cross_model import CROSS
    from pipeline.infra.artifacts import ArtifactStore
    from pipeline.stages._environment import config_inputs, environment_of, recorded_paths
    from pipeline.stages.evaluate import closed_loop_settings, tracking_settings

    cfg = compose("stage=evaluate", *overrides)
    store = ArtifactStore(cfg.paths.artifact_dir)

    def fitted(config):
        return (store.require("fit_model", keys.key("fit_model", config)),
                store.require("align", keys.key("align", config)))

    def tracking_plants(config, models, twins):
        settings = closed_loop_settings(config)
        inputs = config_inputs(config, *fitted(config))
        env, _, eval_params = environment_of(config, inputs)
        key = jax.random.fold_in(jax.random.key(int(config.evaluation.seed)), 7)
        if not twins:
            settings = settings.only_in_models()
        return (tracking_settings(config, recorded_paths(inputs)),
                _plants(settings, env, eval_params, jax.random.fold_in(key, 1), models, twins))

    twins = {f"twin {name}": twin_physics(str(name), cfg.paths.artifact_dir)
             for name in cfg.evaluation.twins}
    out = {"all runs": tracking_plants(cfg, {}, twins)}
    for direction, (train, test) in chain.cross_model_folds(cfg).items():
        other = load_dynamics(fitted(test)[0].file("model.msgpack"))
        tracking, plants = tracking_plants(train, {CROSS: other}, {})
        out[direction] = (tracking, {("own" if name == "learned" else name): plant
                                     for name, plant in plants.items()})
    return cfg, out


def main(argv=None) -> None:
    args = parse_args(argv)
    from pipeline.studies import start_study

    if start_study(args, report):
        return
    import jax
    import jax.numpy as jnp

    from pipeline.arm import references
    from pipeline.evaluation.closed_loop import _starts
    from pipeline.evaluation.tracking import episode_references, tracking_metrics
    from pipeline.studies import append_jsonl

    cfg, protocols = plant_sets(args.overrides)
    episodes = int(cfg.evaluation.num_episodes)
    rows = []
    chosen = args.protocols.split(",") if args.protocols else list(protocols)
    unknown = [name for name in chosen if name not in protocols]
    if unknown:
        raise SystemExit(f"--protocols: unknown {unknown}; this config has {list(protocols)}")
    for protocol in chosen:
        tracking, plants = protocols[protocol]
        for plant_name, (env, env_params) in plants.items():
            control_hz = float(env.control_hz)
            steps = round(float(tracking.seconds) * control_hz)
            # the first scored row, as tracking_metrics picks it
            settle = math.ceil(float(tracking.settle_seconds) * control_hz - 1e-9)
            times = jnp.arange(steps + 1, dtype=jnp.float32) / control_hz
            carries, positions = _starts(env_params, episodes)
            shapes = episode_references(tracking, np.asarray(env_params.goal_set), episodes)
            for name, stacked in shapes.items():
                targets = jax.vmap(references.positions, in_axes=(0, None))(stacked, times)
                started = time.perf_counter()
                _, found, held = jax.block_until_ready(jitted_optimal_commands()(
                    env, env_params, carries, env_params.preload, targets, settle,
                    args.iterations, args.lr))
                seconds = time.perf_counter() - started  # the first of a plant compiles
                start = np.asarray(positions)[:, None]
                scores = {kind: tracking_metrics(np.concatenate([start, np.asarray(p)], 1),
                                                 np.asarray(targets), control_hz,
                                                 float(tracking.settle_seconds))
                          for kind, p in (("oracle", found), ("preload", held))}
                row = {"protocol": protocol, "plant": plant_name, "reference": name,
                       "episodes": episodes, "seconds": seconds,
                       **{f"{kind}_median_rmse_mm": float(table["rmse_mm"].median())
                          for kind, table in scores.items()},
                       "oracle_p90_rmse_mm": float(scores["oracle"]["rmse_mm"].quantile(0.9)),
                       "oracle_median_offset_mm": float(scores["oracle"]["offset_mm"].median()),
                       "oracle_within_1mm": float(scores["oracle"]["within_1mm"].mean())}
                log.info("%s", row)
                rows.append(row)
    record = {"command": "python -m experiments.tracking_oracle " + shlex.join(sys.argv[1:]),
              "iterations": args.iterations, "lr": args.lr, "rows": rows}
    append_jsonl(args.out, record)
    print(report(args.out))


def report(path: str) -> str:
    """Per record of ``path``: the oracle's and the preload's median RMSE per plant and
    reference."""
    records = [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]
    lines = []
    for record in records:
        lines += [f"`{record['command']}` ({record['iterations']} Adam steps, lr "
                  f"{record['lr']:g} kPa)", "",
                  "| protocol | plant | reference | oracle: median / p90 RMSE [mm] | steady offset "
                  "[mm] | within 1 mm | preload: median RMSE [mm] |", "|---|---|---|---|---|---|---|"]
        for row in record["rows"]:
            lines.append(f"| {row['protocol']} | {row['plant']} | {row['reference']} | "
                         f"{row['oracle_median_rmse_mm']:.2f} / {row['oracle_p90_rmse_mm']:.2f} | "
                         f"{row['oracle_median_offset_mm']:.2f} | "
                         f"{100 * row['oracle_within_1mm']:.0f} % | "
                         f"{row['preload_median_rmse_mm']:.2f} |")
        lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
