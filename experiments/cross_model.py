"""Cross-model protocol: policies trained in the model of one group of real runs, evaluated in
the model of another, disjoint group (both directions), per robustness variant.

    python -m experiments.cross_model [--variants plain ensemble randomized both incremental
        incremental_randomized incremental_randomized_ensemble
        incremental_randomized_ensemble_agreed]
        [--directions A->B B->A] [--seeds 4] [--agent ppo_ff|ppo_rnn|apg|apg_rnn]
        [--ppo-steps N] [--ensemble-seeds 3]
        [--goal-agreement-mm MM] [--twin sim_sorolex] [--reach] [--twin-tune STEPS]
        [--quick]
        [--set KEY=VALUE ...]

The recorded runs (``robot=sorolex_csv``, ``../shared/data/sorolex``) are split into two groups
(sorted by name, alternating: ``A`` the even positions, ``B`` the odd ones; or ``--group-a``).
Each group is its own dataset (``robot.files``), with its own fit_model artifact. For each
direction (train in A, evaluate in B; and B in A) and each variant, ``--agent`` (default
``ppo_ff``) is trained in the
training group's model (``experiment=real_arm``'s env and agent settings) and the evaluate stage
rolls it out on the training group's held-out goals in its own model (``own``) and in the other
group's model (``cross``, through ``evaluation.models``). Variants, made of
``experiment=real_arm``'s robustness settings (its incremental actions, its per-episode
randomization of the plant, ``env.randomization``, and its price on command changes,
``env.command_change_cost_mm_per_kpa``, which only the ``incremental_randomized`` variants keep):

- ``plain``: absolute actions, no randomization (the model as it is);
- ``ensemble``: plain, in an ensemble of ``--ensemble-seeds`` model seeds (``env.ensemble_seeds``);
- ``randomized``: absolute actions, the plant randomized;
- ``both``: the ensemble, randomized;
- ``incremental``: incremental actions (integral action), no randomization;
- ``incremental_randomized``: incremental actions, randomized, in one model;
- ``incremental_randomized_ensemble``: that in the ensemble of model seeds: ``experiment=real_arm``
  as it is (with ``--ensemble-seeds`` seeds);
- ``incremental_randomized_ensemble_agreed``: that, trained on conservative goals only, those
  where the ensemble's members agree within ``--goal-agreement-mm`` (``env.goal_agreement_mm``).

The variants without ``ensemble`` in their name train in one model (``env.ensemble_seeds=1``).

Printed per variant and direction: median final distance, its 90th percentile and the success
rates within 1 and 3 mm (all seeds' episodes together), own and cross; the hold after the first
arrival within 1 mm (the share of episodes that arrived, and of those the share that ended within
1.5 mm, ``held_arrivals``; :func:`pipeline.evaluation.metrics.hold_metrics`); the share of seeds whose
median is within 1 mm across models; and the seed ``stage=control`` would deploy (the best in
its training's last held-out evaluation) with its own and cross medians and its success within 1
mm across models; with ``--reach``, per plant the share of the goals that some constant
command inside the arm's limits holds within 1 mm by the episode's end, and of the misses the
share on such goals (:mod:`pipeline.evaluation.reachability`); with ``--twin-tune STEPS``, a
second row per direction: the policies fine-tuned in the twin by analytic policy gradients
through it, evaluated the same way. The table is also written to
``<output-dir>/cross_model/results.csv``.
Everything goes through the pipeline's router (artifacts reused when present). ``--quick``
shrinks every stage to check the script in minutes (the numbers then mean nothing). ``--set
KEY=VALUE ...`` adds pipeline overrides for every stage (say ``agent.lr=3e-4``), beside the
variant's; the table's ``overrides`` column lists them.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import Any

import pandas as pd

from pipeline.studies import run_stage

VARIANTS = ("plain", "ensemble", "randomized", "both", "incremental", "incremental_randomized",
            "incremental_randomized_ensemble", "incremental_randomized_ensemble_agreed")
QUICK = ["model.num_steps=20", "model.eval_every=10", "model.checkpoint_every=10",
         "dataset.window=32", "agent.num_envs=16", "agent.num_steps=8", "agent.num_evals=1",
         "agent.eval_envs=4", "agent.progress=false", "env.goal_every=20",
         "env.reset_bank_size=8", "evaluation.num_episodes=8",
         "evaluation.consecutive_episodes=1", "evaluation.num_consecutive_goals=2"]
QUICK_PPO_STEPS = 1024  # --quick's budget per seed, unless --ppo-steps
DIRECTIONS = ("A->B", "B->A")
# policy types it trains: PPO, or analytic policy gradients through the model (agent=apg)
AGENTS = ("ppo_ff", "ppo_rnn", "apg", "apg_rnn")
GOAL_AGREEMENT_MM = 1.0  # the agreed variant's default env.goal_agreement_mm
METRICS = ("median_final_mm", "p90_final_mm", "success_1mm", "success_3mm", "arrived_1mm",
           "held_arrivals", "within_1mm_after_arrival", "median_max_after_arrival_mm")


def groups(data_dir: Path, group_a: list[str] | None) -> tuple[list[str], list[str]]:
    """Two disjoint groups of recording names (A: even positions of the sorted names, or
    ``group_a``; B: the rest)."""
    names = sorted(p.name for p in data_dir.glob("Step_control_*.csv"))
    if len(names) < 2:
        raise SystemExit(f"need at least two recordings in {data_dir}, found {names}")
    first = [n for n in names if n in set(group_a)] if group_a else names[0::2]
    second = [n for n in names if n not in set(first)]
    if not first or not second:
        raise SystemExit(f"both groups need a run: A={first}, B={second}")
    return first, second


def variant_overrides(variant: str, ensemble_seeds: int,
                      goal_agreement_mm: float = GOAL_AGREEMENT_MM) -> list[str]:
    """The overrides of ``variant`` on top of ``experiment=real_arm`` (incremental, randomized,
    command changes priced): the variants before the price went without it."""
    from pipeline.schemas import no_randomization_overrides

    unpriced = ["env.command_change_cost_mm_per_kpa=0"]
    absolute = ["env.action_mode=absolute", *unpriced]
    no_randomization = no_randomization_overrides()
    ensemble, single = [f"env.ensemble_seeds={ensemble_seeds}"], ["env.ensemble_seeds=1"]
    return {"plain": absolute + no_randomization + single,
            "ensemble": absolute + no_randomization + ensemble, "randomized": absolute + single,
            "both": absolute + ensemble,
            "incremental": unpriced + no_randomization + single,
            "incremental_randomized": single, "incremental_randomized_ensemble": ensemble,
            "incremental_randomized_ensemble_agreed": [
                *ensemble, f"env.goal_agreement_mm={goal_agreement_mm}"]}[variant]


def measure(output_dir: Path, base: list[str], train: list[str], test: list[str],
            variant: str, ensemble_seeds: int, agent: str = "ppo_ff",
            goal_agreement_mm: float = GOAL_AGREEMENT_MM, twin: str | None = None,
            reach: Any = None, twin_tune_steps: int = 0) -> list[dict[str, Any]]:
    """``agent`` trained in ``train``'s model (``variant``), evaluated in its own and in
    ``test``'s model (and on the calibrated ``twin``, ``evaluation.twins``, where given: the
    ``twin_*`` figures): one row of the results table. Beside the figures over every seed's
    episodes: the share of seeds whose median is within 1 mm (own and cross), and the figures
    of the seed that ``stage=control`` would deploy (the best in the training's last held-out
    evaluation, ``pipeline.rl.policy_io.best_seed``). With ``reach``
    (:class:`pipeline.evaluation.reachability.ReachSettings`): where the goals can be held at
    all on each plant, and where the misses are (:func:`reach_figures`). With
    ``twin_tune_steps``, a second row: the policies fine-tuned in the twin
    (:func:`twin_tuned`, kept in ``<output-dir>/cross_model/twin_tuned_<evaluate key>_<steps>
    .parquet``), evaluated the same way (variant ``<variant>, tuned in the twin``)."""
    from pipeline.rl.policy_io import best_seed

    files = lambda names: f"robot.files=[{','.join(names)}]"  # noqa: E731
    where = f"paths.output_dir={output_dir}"
    other = run_stage("fit_model", where, *base, files(test))["fit_model"]
    overrides = [where, *base, files(train),
                 *variant_overrides(variant, ensemble_seeds, goal_agreement_mm),
                 f"evaluation.policies=[{agent}]", "evaluation.baselines=[preload]",
                 "evaluation.plant=false", "evaluation.cross_model=false",
                 f"evaluation.models=[{other.path}]", f"evaluation.twins=[{twin or ''}]"]
    evaluated = run_stage("evaluate", *overrides)
    every = pd.read_parquet(evaluated["evaluate"].file("episodes.parquet"))
    plants = {"learned": "own", f"model {other.path.name}": "cross"}
    if twin:
        plants[f"twin {Path(twin).name}"] = "twin"
    evaluation = evaluated["train_ppo"].file("evaluation.parquet")
    seed = best_seed(pd.read_parquet(evaluation), evaluation)  # the one stage=control drives
    row: dict[str, Any] = {"agent": agent, "variant": variant, "train": "+".join(train),
                           "test": "+".join(test), "deployed_seed": seed,
                           **plant_figures(every, agent, seed, plants)}
    folder = output_dir / "cross_model"
    if reach is not None:
        row.update(reach_figures(overrides, evaluated, other, twin, every, agent, reach, folder))
    if not (twin and twin_tune_steps):
        return [row]
    path = folder / f"twin_tuned_{evaluated['evaluate'].path.name}_{int(twin_tune_steps)}.parquet"
    if path.is_file():
        tuned = pd.read_parquet(path)
    else:
        tuned = twin_tuned(overrides, evaluated, other, twin, agent, twin_tune_steps)
        folder.mkdir(parents=True, exist_ok=True)
        tuned.to_parquet(path)
    name = f"{agent}+twin"
    tuned_row = {**{k: row[k] for k in ("agent", "train", "test", "deployed_seed")},
                 "variant": f"{variant}, tuned in the twin",
                 **plant_figures(tuned, name, seed, plants)}
    if reach is not None:
        tuned_row.update(reach_figures(overrides, evaluated, other, twin, tuned, name, reach,
                                       folder))
    return [row, tuned_row]


def plant_figures(episodes: pd.DataFrame, controller: str, seed: int,
                  plants: dict[str, str]) -> dict[str, float]:
    """``<own|cross|twin>_<figure>`` of ``controller``'s episodes (evaluate's per-episode
    table; ``plants`` maps its plant names to own, cross and twin) over every seed, and of the
    deployed ``seed`` (:func:`pipeline.evaluation.cross_model.across_models`)."""
    from pipeline.evaluation.cross_model import across_models

    mine = episodes[episodes["controller"] == controller].assign(
        plant=lambda frame: frame["plant"].map(plants))
    summary = across_models(mine, {controller: seed}).set_index("plant")
    row = {}
    for where in plants.values():
        for metric in (*METRICS, "seeds_median_within_1mm", "deployed_median_final_mm",
                       "deployed_success_1mm"):
            if metric in summary:  # an evaluation written before the hold metrics has none
                row[f"{where}_{metric}"] = float(summary.loc[where, metric])
    return row


def reach_figures(overrides: list[str], evaluated: dict[str, Any], other: Any,
                  twin: str | None, episodes: pd.DataFrame, agent: str, settings: Any,
                  folder: Path) -> dict[str, float]:
    """Where the evaluation's goals can be held at all, and where ``agent``'s misses are.

    The evaluate stage's plants (own model, the other group's, the twin), goals and start
    states rebuilt from its config (``overrides``); on each, per episode, the nearest distance
    any constant command inside the arm's limits holds it at by the episode's end
    (:func:`pipeline.evaluation.reachability.evaluation_reach`, ``settings``). Checked against
    the evaluation itself: holding the preload must end where its ``preload`` baseline ended.
    Kept in ``folder/reach_<model>_<other model>_<twin>_<search>.parquet`` (the same for
    every policy type of the direction). With a margin (``settings.margin_kpa``) on the twin
    alone. Returns ``<own|cross|twin>_<figure>`` of
    :func:`~pipeline.evaluation.reachability.split_misses` for ``agent``.
    """
    from pipeline.evaluation.reachability import preload_mismatch_mm, split_misses

    name = (f"reach_{evaluated['fit_model'].path.name}_{other.path.name}_"
            f"{Path(twin).name if twin else 'none'}_{settings.grid_points}x"
            f"{settings.newton_rounds}x{settings.refine_rounds}x{settings.starts}+"
            f"{settings.margin_kpa:g}.parquet")
    path = folder / name
    if path.is_file():
        reach = pd.read_parquet(path)
    else:
        reach = _reach_table(overrides, evaluated, other, twin, settings)
        mismatch = preload_mismatch_mm(reach, episodes[episodes["plant"].isin(reach["plant"])])
        if not mismatch < 0.01:
            raise SystemExit(f"the reach's plants are not the evaluation's: holding the preload "
                             f"ends up to {mismatch:.4f} mm from where the evaluation's preload "
                             f"baseline ended ({evaluated['evaluate'].path})")
        folder.mkdir(parents=True, exist_ok=True)
        reach.to_parquet(path)
    plants = {"learned": "own", f"model {other.path.name}": "cross"}
    if twin:
        plants[f"twin {Path(twin).name}"] = "twin"
    mine = episodes[(episodes["controller"] == agent) & episodes["plant"].isin(reach["plant"])]
    split = split_misses(mine, reach)
    row = {}
    for record in split.itertuples():
        for column in ("reachable_goals", "misses", "misses_reachable",
                       "median_final_reachable_mm", "success_reachable", "median_reach_mm",
                       "median_excess_unreachable_mm"):
            row[f"{plants[record.plant]}_{column}"] = float(getattr(record, column))
    return row


def _reach_table(overrides: list[str], evaluated: dict[str, Any], other: Any,
                 twin: str | None, settings: Any) -> pd.DataFrame:
    """:func:`pipeline.evaluation.reachability.evaluation_reach` on the plants of the evaluate
    stage's config ``overrides``, built as the stage builds them."""
    from pipeline.arm.twins import twin_physics
    from pipeline.config import compose
    from pipeline.dynamics.checkpoints import load_dynamics
    from pipeline.evaluation.reachability import evaluation_episodes, evaluation_reach
    from pipeline.stages._environment import config_environment
    from pipeline.stages.evaluate import closed_loop_settings

    cfg = compose("stage=evaluate", *overrides)
    env, _, eval_params = config_environment(cfg, evaluated["fit_model"], evaluated["align"])
    models = {f"model {other.path.name}": load_dynamics(other.file("model.msgpack"))}
    twins = ({f"twin {Path(twin).name}": twin_physics(twin, cfg.paths.artifact_dir)}
             if twin else {})
    plants, goals = evaluation_episodes(closed_loop_settings(cfg), env, eval_params, models,
                                        twins)
    if settings.margin_kpa:  # a bound for the twin's hysteresis: the twin alone
        plants = {name: plant for name, plant in plants.items() if name.startswith("twin ")}
    return evaluation_reach(plants, goals, settings)


def print_table(table: pd.DataFrame) -> None:
    header = (f"{'variant':<50}{'dir':<7}{'own median':>11}{'p90':>7}{'<1mm':>7}{'<3mm':>7}"
              f"{'cross median':>14}{'p90':>7}{'<1mm':>7}{'<3mm':>7}{'seeds <1mm':>11}"
              f"{'deployed seed':>14}{'own':>6}{'cross':>7}{'<1mm':>7}")
    print(header)
    print("-" * len(header))
    for row in table.itertuples():
        print(f"{row.variant:<50}{row.direction:<7}{row.own_median_final_mm:>11.2f}"
              f"{row.own_p90_final_mm:>7.2f}{row.own_success_1mm:>7.2f}"
              f"{row.own_success_3mm:>7.2f}{row.cross_median_final_mm:>14.2f}"
              f"{row.cross_p90_final_mm:>7.2f}{row.cross_success_1mm:>7.2f}"
              f"{row.cross_success_3mm:>7.2f}{row.cross_seeds_median_within_1mm:>11.2f}"
              f"{row.deployed_seed:>14d}{row.own_deployed_median_final_mm:>6.2f}"
              f"{row.cross_deployed_median_final_mm:>7.2f}{row.cross_deployed_success_1mm:>7.2f}")
    if "twin_median_final_mm" in table:
        print("\non the calibrated twin: median / p90 [mm], within 1 / 3 mm, deployed seed's "
              "median")
        for row in table.itertuples():
            print(f"{row.variant:<50}{row.direction:<7}{row.twin_median_final_mm:>7.2f}"
                  f"{row.twin_p90_final_mm:>7.2f}{row.twin_success_1mm:>7.2f}"
                  f"{row.twin_success_3mm:>7.2f}{row.twin_deployed_median_final_mm:>7.2f}")
    if any(f"{p}_reachable_goals" in table for p in ("own", "cross", "twin")):
        print_reach(table)
    print("\nthe hold: share of episodes ever within 1 mm / of those, the share ended within "
          "1.5 mm, per plant")
    plants = [p for p in ("own", "cross", "twin") if f"{p}_held_arrivals" in table]
    print(f"{'variant':<50}{'dir':<7}" + "".join(f"{p + ' arrived':>15}{p + ' held':>12}"
                                               for p in plants))
    for row in table.itertuples():
        print(f"{row.variant:<50}{row.direction:<7}" + "".join(
            f"{getattr(row, f'{p}_arrived_1mm'):>15.2f}{getattr(row, f'{p}_held_arrivals'):>12.2f}"
            for p in plants))


def twin_tuned(overrides: list[str], evaluated: dict[str, Any], other: Any, twin: str,
               agent: str, steps: int) -> pd.DataFrame:
    """``agent``'s policies (every seed) fine-tuned in the calibrated ``twin`` by analytic
    policy gradients through it (``pipeline.rl.apg``: windows of 10 control periods, lr 1e-3,
    ``steps`` environment steps per seed), then evaluated as the evaluate stage of
    ``overrides`` does (the same goals and start states, own model, the other group's, the
    twin): its per-episode table, the controller named ``<agent>+twin``.

    The twin is trained in as the training group's model is: observed with the same
    normalization, started where its physics rest it (as the evaluation's twin), the training
    goals, the training randomization of the plant (gain, offset, delay, rest offset, drift);
    its physics the twin's nominal ones (the evaluation's twin)."""
    import dataclasses

    import jax

    from pipeline.arm.twins import twin_physics, twin_sim_params
    from pipeline.config import compose
    from pipeline.dynamics.checkpoints import load_dynamics
    from pipeline.evaluation.closed_loop import Policy, _sim_env, run_evaluation, twin_env_params
    from pipeline.rl.envs.plants import SimPlantParams
    from pipeline.rl.policy_io import load_policy
    from pipeline.rl.ppo import train_seeds
    from pipeline.schemas import AgentConfig
    from pipeline.stages._environment import config_environment
    from pipeline.stages.evaluate import closed_loop_settings

    cfg = compose("stage=evaluate", *overrides)
    env, train_params, eval_params = config_environment(cfg, evaluated["fit_model"],
                                                        evaluated["align"])
    settings = closed_loop_settings(cfg)
    settings = dataclasses.replace(settings, evaluation=dataclasses.replace(
        settings.evaluation, num_consecutive_goals=0))
    physics = twin_physics(twin, cfg.paths.artifact_dir)
    sim = twin_sim_params(physics)
    twin_env = _sim_env(settings, env, sim.mocap_hz)
    plant = SimPlantParams(sim, eval_params.preload)
    shared = {"safe_set": eval_params.safe_set, "obs_mean": train_params.obs_mean,
              "obs_scale": train_params.obs_scale, "settings": settings.env}
    tune_key, check_key = jax.random.split(jax.random.key(int(cfg.seed)))
    tune_params = twin_env_params(twin_env, plant, key=tune_key, goal_set=train_params.goal_set,
                                  randomization_params=train_params.randomization, **shared)
    check_params = twin_env_params(twin_env, plant, key=check_key,
                                   goal_set=eval_params.goal_set, **shared)
    network, params, _ = load_policy(evaluated["train_ppo"].file("policy.msgpack"))
    spec = evaluated["train_ppo"].manifest["spec"]["agent"]
    tuning = AgentConfig.from_any({
        **spec, "trainer": "apg", "num_steps": 10, "lr": 1.0e-3, "max_grad_norm": 1.0,
        "total_timesteps": int(steps), "recurrent_total_timesteps": None, "num_evals": 4,
        "eval_envs": 64}, progress=False)
    tuning.check()
    tuned = train_seeds(tuning, twin_env, tune_params, check_params, seed=int(cfg.seed) + 1,
                        desc=f"{agent} in {twin}", init_params=params)
    models = {f"model {other.path.name}": load_dynamics(other.file("model.msgpack"))}
    results = run_evaluation(settings, {f"{agent}+twin": Policy(network, tuned.params)}, env,
                             eval_params, models, {f"twin {Path(twin).name}": physics})
    return results["tables"]["episodes"]


def print_reach(table: pd.DataFrame) -> None:
    """The reach's figures per plant: the share of episodes whose goal a constant admissible
    command holds within 1 mm, of the misses (> 1 mm at the end) the share on such goals, and
    the median final distance and success within 1 mm over the episodes of such goals."""
    print("\nreach: goals held within 1 mm by some admissible constant command / misses on "
          "them / median [mm] and <= 1 mm over them")
    plants = [p for p in ("own", "cross", "twin") if f"{p}_reachable_goals" in table]
    print(f"{'variant':<50}{'dir':<7}" + "".join(
        f"{p + ' reach':>12}{'on reach':>10}{'median':>8}{'<1mm':>7}" for p in plants))
    for row in table.itertuples():
        print(f"{row.variant:<50}{row.direction:<7}" + "".join(
            f"{getattr(row, f'{p}_reachable_goals'):>12.2f}"
            f"{getattr(row, f'{p}_misses_reachable'):>10.2f}"
            f"{getattr(row, f'{p}_median_final_reachable_mm'):>8.2f}"
            f"{getattr(row, f'{p}_success_reachable'):>7.2f}" for p in plants))


def main(argv: list[str] | None = None) -> None:
    from pipeline.config import PROJECT_ROOT, sorolex_dir
    from pipeline.schemas import budget_overrides

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--output-dir", type=Path, default=PROJECT_ROOT / "outputs",
                        help="the pipeline's paths.output_dir (its artifacts are reused)")
    parser.add_argument("--data-dir", type=Path, default=sorolex_dir())
    parser.add_argument("--group-a", nargs="*", default=None,
                        help="recording names of group A (default: every other one)")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    parser.add_argument("--directions", nargs="+", default=list(DIRECTIONS), choices=DIRECTIONS,
                        help="train in A and evaluate in B (A->B), the reverse (B->A), or both")
    parser.add_argument("--seeds", type=int, default=4, help="PPO seeds per variant")
    parser.add_argument("--agent", default="ppo_ff", choices=AGENTS)
    parser.add_argument("--ppo-steps", type=int, default=None,
                        help="training environment steps per seed (default: "
                             "experiment=real_arm's budget of the policy type)")
    parser.add_argument("--ensemble-seeds", type=int, default=3,
                        help="model seeds of the ensemble variants")
    parser.add_argument("--goal-agreement-mm", type=float, default=GOAL_AGREEMENT_MM,
                        help="the agreed variant's env.goal_agreement_mm")
    parser.add_argument("--twin", default=None,
                        help="also evaluate on this calibrated twin (evaluation.twins: a "
                             "simulated robot config's name, e.g. sim_sorolex, or a calibrate "
                             "artifact's key or folder)")
    parser.add_argument("--set", dest="overrides", nargs="+", action="extend", default=[],
                        metavar="KEY=VALUE",
                        help="further pipeline overrides for every stage (agent.lr=3e-4 ...)")
    parser.add_argument("--reach", action="store_true",
                        help="also find, per plant, the goals any constant command inside the "
                             "arm's limits holds within 1 mm, and split the misses by them")
    parser.add_argument("--reach-grid", type=int, nargs=4, default=(9, 24, 4, 12),
                        metavar=("POINTS", "ROUNDS", "STARTS", "NEWTON"),
                        help="the reach's grid points per valve, local-search rounds, the "
                             "grid points it starts from and its Gauss-Newton steps")
    parser.add_argument("--reach-margin", type=float, default=0.0, metavar="KPA",
                        help="admit commands this far beyond each valve's limits (3x beyond "
                             "the sum's); twice the twin's hysteresis play admits every hold "
                             "any controller can reach on it; with a margin, the twin alone")
    parser.add_argument("--twin-tune", type=int, default=0, metavar="STEPS",
                        help="also fine-tune the policies in the --twin by analytic policy "
                             "gradients for STEPS env steps per seed and evaluate them again")
    parser.add_argument("--quick", action="store_true",
                        help="shrink every stage (checks the script; the numbers mean nothing)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s][%(name)s] %(message)s")
    group_a, group_b = groups(args.data_dir, args.group_a)
    print(f"group A: {group_a}\ngroup B: {group_b}", flush=True)
    steps = QUICK_PPO_STEPS if args.quick and args.ppo_steps is None else args.ppo_steps
    reach = None
    if args.reach:
        from pipeline.evaluation.reachability import ReachSettings

        reach = ReachSettings(*args.reach_grid, margin_kpa=args.reach_margin)
    base = ["experiment=real_arm", f"agent={args.agent}", f"robot.data_dir={args.data_dir}",
            f"agent.num_seeds={args.seeds}", *(QUICK if args.quick else []),
            *([] if steps is None else budget_overrides(steps)), *args.overrides]
    rows = []
    splits = {"A->B": (group_a, group_b), "B->A": (group_b, group_a)}
    for direction in args.directions:
        train, test = splits[direction]
        for variant in args.variants:
            measured = measure(args.output_dir, base, train, test, variant,
                               args.ensemble_seeds, args.agent, args.goal_agreement_mm,
                               args.twin, reach, args.twin_tune)
            rows += [{"direction": direction, **row, "overrides": " ".join(args.overrides)}
                     for row in measured]
    table = pd.DataFrame(rows)
    out = args.output_dir / "cross_model"
    out.mkdir(parents=True, exist_ok=True)
    table.to_csv(out / "results.csv", index=False)
    print(f"\n{args.agent} final distance [mm] and success rates, own model vs the other group's "
          f"({args.seeds} seeds x evaluation.num_episodes episodes each)")
    print_table(table)
    print(f"\n{out / 'results.csv'}")


if __name__ == "__main__":
    main()
