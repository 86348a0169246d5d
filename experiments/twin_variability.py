"""How much the arm's physics differ between runs: a few parameters refitted per run.

Starts every run from the calibrated physics of ``robot=sim_sorolex`` (the fit on all runs,
``conf/robot/sim_sorolex.yaml``) and refits a subset of parameters (``--fitted``) and the run's
rest offset on that run alone, by Adam through the simulator (the calibration's
parameterization, :mod:`pipeline.arm.calibration`), all runs in one vmapped program. Prints per
run the refitted values and its open-loop error before and after, then the spread between runs
(what ``physics.session_std`` of a simulated arm is read off).

The same refit on runs of the simulated arm itself (``--robot sim_sorolex`` with its own
overrides) measures the estimator's spread when the physics do not differ.

Usage (the runs through ``stage=align`` with the same overrides, reused when there)::

    python -m experiments.twin_variability [--robot sorolex_csv] [--steps 150] [override ...]
"""

from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp
import numpy as np
import optax
from omegaconf import OmegaConf

from pipeline.arm import calibration as calib
from pipeline.arm import sim_arm
from pipeline.config import compose
from pipeline.studies import recorded_runs

HZ = 20.0
SUBSTEPS = 2
FITTED = ("chamber_angles_deg", "chamber_gains", "mean_stiffening_per_kpa", "pressure_tau_s",
          "natural_freq_hz", "damping_ratio", "hysteresis_kpa", "elong_gain")


def calibrated_physics() -> dict:
    cfg = compose("robot=sim_sorolex")
    physics = calib.sim_physics_values(cfg.robot.physics)
    return {k: v for k, v in physics.items() if k in sim_arm.PHYSICS_VALUES}


def template_of(physics: dict) -> sim_arm.SimParams:
    robot = OmegaConf.create({
        "physics": {**physics, "substeps": SUBSTEPS},
        "mocap": {"rate_hz": HZ, "noise_std_m": 0.0, "jitter_std_s": 0.0, "drop_prob": 0.0,
                  "burst_prob": 0.0, "burst_len": 1}})
    return sim_arm.SimParams.from_config(robot)


def per_run_fit(template, param, batch: calib.RunBatch, z0: np.ndarray, steps: int, lr: float):
    """Each run its own ``z`` and offset: ``(z [R, D], offsets [R, 3] m, loss [R] mm²)``."""

    def loss_one(z, offset_mm, commands, positions, mask, preload):
        params = template.with_physics(param.to_physics(z))
        state = sim_arm.settled_state(params, preload, jnp.zeros(3))
        predicted = sim_arm.predict_positions(params, state, commands)
        error = 1e3 * predicted + offset_mm - 1e3 * positions
        return (jnp.sum(error**2, -1) * mask).sum() / mask.sum()

    arrays = calib.batch_arrays(batch)
    rest = calib.rest_poses(template, param, z0[None], batch.preload)[0]
    offsets0 = 1e3 * (batch.positions[:, 0] - rest)
    optimizer = optax.chain(optax.clip_by_global_norm(10.0),
                            optax.adam(optax.cosine_decay_schedule(lr, steps, alpha=0.05)))
    losses = jax.vmap(loss_one)
    grad = jax.vmap(jax.value_and_grad(loss_one, argnums=(0, 1)))

    @jax.jit
    def fit(z, offsets):
        variables = (z, offsets)
        state = jax.vmap(optimizer.init)(variables)

        def step(carry, _):
            variables, state = carry
            loss, grads = grad(*variables, arrays["commands"], arrays["positions"],
                               arrays["mask"], arrays["preload"])
            updates, state = jax.vmap(optimizer.update)(grads, state, variables)
            return (optax.apply_updates(variables, updates), state), loss

        (variables, _), trace = jax.lax.scan(step, (variables, state), None, steps)
        final = losses(*variables, arrays["commands"], arrays["positions"], arrays["mask"],
                       arrays["preload"])
        return variables, trace, final

    z = jnp.tile(jnp.asarray(z0, jnp.float32)[None], (len(batch.run_ids), 1))
    (z, offsets), trace, final = jax.device_get(fit(z, jnp.asarray(offsets0, jnp.float32)))
    return np.asarray(z), np.asarray(offsets) * 1e-3, np.asarray(trace), np.asarray(final)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--robot", default="sorolex_csv")
    parser.add_argument("--steps", type=int, default=150)
    parser.add_argument("--lr", type=float, default=0.05)
    parser.add_argument("--fitted", default=",".join(FITTED))
    parser.add_argument("--out", default=None, help="write the per-run values as JSON here")
    parser.add_argument("overrides", nargs="*")
    args = parser.parse_args()
    names = args.fitted.split(",")
    physics = calibrated_physics()
    _, runs = recorded_runs(f"robot={args.robot}", *args.overrides, rate_hz=HZ, grid="clock")
    batch = calib.RunBatch.from_runs(runs)
    template = template_of(physics)
    param = calib.Parameterization.create(names, physics)
    z0 = param.from_physics(physics)
    z, offsets, trace, final = per_run_fit(template, param, batch, z0, args.steps, args.lr)
    values = [{k: np.atleast_1d(np.asarray(v, np.float64))
               for k, v in param.to_physics(jnp.asarray(z_r)).items()} for z_r in z]
    print(f"{len(runs)} runs of robot={args.robot}, {args.steps} Adam steps, refitted {names}")
    print("run | rms before mm | rms after mm | " + " | ".join(names))
    for i, run in enumerate(runs):
        cells = [", ".join(f"{x:.4g}" for x in values[i][n]) for n in names]
        print(f"{run.run_id} | {np.sqrt(trace[0, i]):.2f} | {np.sqrt(final[i]):.2f} | "
              + " | ".join(cells))
    print("\nspread between runs (std over runs; relative: std of the log)")
    spread = {}
    for n in names:
        stack = np.stack([v[n] for v in values])  # [R, k]
        std = stack.std(0)
        rel = np.log(np.abs(stack)).std(0)
        base = np.atleast_1d(np.asarray(physics[n], np.float64))
        print(f"  {n}: calibrated {np.round(base, 5).tolist()}, per-run mean "
              f"{np.round(stack.mean(0), 5).tolist()}, std {np.round(std, 5).tolist()}, "
              f"log std {np.round(rel, 4).tolist()}")
        spread[n] = {"std": std.tolist(), "log_std": rel.tolist(), "mean": stack.mean(0).tolist()}
    print(f"  rest offsets: std {np.round(offsets.std(0) * 1e3, 3).tolist()} mm")
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"runs": [r.run_id for r in runs], "names": names,
                       "values": [{k: v.tolist() for k, v in d.items()} for d in values],
                       "rms_before_mm": np.sqrt(trace[0]).tolist(),
                       "rms_after_mm": np.sqrt(final).tolist(), "spread": spread}, f, indent=1)


if __name__ == "__main__":
    main()
