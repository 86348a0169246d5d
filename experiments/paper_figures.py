"""The paper's figures (RoboSoft 2024, Figs. 4-8) from this project's own artifacts.

    python -m experiments.paper_figures [--seeds 20] [--ppo-steps 102400] [--out DIR]
                                        [--set KEY=VALUE ...]
    make figures

``--set`` adds Hydra overrides to every stage the figures run (a shrunk run for the tests:
fewer model steps, fewer recordings).

Each figure is made from the artifacts of the pipeline (``pipeline.__main__.run``: reused when
they are there, produced when they are missing), sized to run in minutes on two CPU cores. What
was run, and what was made smaller than in the paper, is written under each figure and in
``captions.md`` beside them; where the result here differs from the paper's claim, the caption
says so.

- Fig. 4: the exploration walk for several alpha (the collect stage's figure, simulated arm).
- Fig. 5: task-space trajectories of the simulated arm driven by the walk, several alpha.
- Fig. 6: training and validation loss of the dynamics model on the real runs, windows drawn in
  permuted against sequential order, training loss smoothed by an EMA with weight 0.025.
- Fig. 7: open-loop reconstruction of a training run and an unseen run (real runs).
- Fig. 8: episodic return of feed-forward and recurrent PPO in the model of the real runs,
  mean ± one std over seeds.
- Tracking (beyond the paper): the references against the paths of the tracking policies and the
  baselines in x-z, and their distance to the reference over time, from the evaluate artifact of
  the config of ``--tracking-set`` (default ``experiment=tracking``) where it is there: it is
  read, never run here (``python -m pipeline experiment=tracking`` makes it); skipped otherwise.

Figs. 6 and 7 show one split of the runs into training and validation runs (``dataset.protocol=
split``): the loss curves need a validation set, which the leave-one-run-out protocol (the default
for recorded data) has per fold only. Fig. 8 trains in the model that ``experiment=real_arm``
trains in (the default protocol: the model fitted to all runs).
"""

from __future__ import annotations

import argparse
import json
import logging
import shlex
import textwrap
import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pipeline.studies import run_stage

log = logging.getLogger("paper_figures")

EMA_WEIGHT = 0.025  # the paper's smoothing of the loss curves (weight of the newest loss)
# what the paper's figures are there to show, checked against what was measured here
CLAIM_FIG6 = "permuted windows generalise better than sequential ones (lower validation loss)"


# Figs. 6 and 7: one seeded split of the runs, so that the losses have validation rows
SPLIT_PROTOCOL = "dataset.protocol=split"


def base_overrides(output_dir: Path, settings: tuple[str, ...] = ()) -> tuple[str, ...]:
    """What every config of the figures gets: ``paths.output_dir`` and the ``--set`` overrides."""
    return (f"paths.output_dir={output_dir}", *settings)


def compose(base: tuple[str, ...], *overrides: str) -> Any:
    """The pipeline's config with ``overrides`` after the ``base`` overrides (``base_overrides``).

    The ``base`` ones come last, so that a shrunk run's settings hold in every figure."""
    from pipeline.config import compose as compose_config

    return compose_config(*overrides, *base)


def reference(*overrides: str) -> Any:
    """A config as the project defines it (no ``--set``): what a shrunk figure is compared to."""
    from pipeline.config import compose as compose_config

    return compose_config(*overrides)


def _captioned(fig, caption: str) -> None:
    """Write ``caption`` under the figure (wrapped to its width), making room for it."""
    lines = textwrap.wrap(caption, int(14.5 * fig.get_figwidth()), break_on_hyphens=False)
    height = fig.get_figheight()
    extra = 0.2 * len(lines) + 0.35
    fig.set_figheight(height + extra)
    images = [ax for ax in fig.axes if ax.get_label() == "image"]
    if images:  # an artifact's own figure: shown above the caption, its own margins kept
        images[0].set_position((0, extra / (height + extra), 1, height / (height + extra)))
    else:
        fig.subplots_adjust(bottom=(extra + 0.45) / (height + extra))
    fig.text(0.01, 0.01, "\n".join(lines), ha="left", va="bottom", fontsize=8, color="0.2",
             family="sans-serif")


def _save(fig, path: Path, caption: str, captions: dict[str, str]) -> Path:
    _captioned(fig, caption)
    fig.savefig(path, dpi=110)
    import matplotlib.pyplot as plt

    plt.close(fig)
    captions[path.name] = caption
    log.info("wrote %s", path)
    return path


def _seconds(duration: float) -> str:
    """How long a step took here, or that its artifact was reused."""
    return f"{duration:.0f} s" if duration >= 5 else "reused"


def _image_figure(png: Path, width_in: float = 11.0):
    """A figure showing an existing PNG (an artifact's own figure) at ``width_in`` inches."""
    import matplotlib.pyplot as plt

    image = plt.imread(png)
    height_px, width_px = image.shape[:2]
    fig = plt.figure(figsize=(width_in, width_in * height_px / width_px))
    ax = fig.add_axes((0, 0, 1, 1), label="image")
    ax.imshow(image)
    ax.axis("off")
    return fig, ax


# ---------------------------------------------------------------------------------------------
# Figs. 4 and 5: the exploration walk and the arm it drives
# ---------------------------------------------------------------------------------------------
def exploration_figures(out: Path, base: tuple[str, ...], captions: dict[str, str]) -> None:
    import matplotlib.pyplot as plt

    cfg = compose(base, "robot=sim")
    alphas = [float(a) for a in cfg.exploration.figure_alphas]
    seconds = int(cfg.exploration.num_steps) / float(cfg.robot.control_hz)
    positions = {}
    walk_png = None
    for alpha in alphas:
        results = run_stage("collect", "robot=sim", "robot.num_runs=1",
                            f"exploration.alpha={alpha}", *base)
        artifact = results["collect"]
        mocap = pd.read_parquet(artifact.file("mocap.parquet"))
        positions[alpha] = mocap[mocap["valid"]] if "valid" in mocap else mocap
        walk_png = walk_png or artifact.file("figures/exploration_alphas.png")

    fig, _ = _image_figure(walk_png, 9.5)
    _save(fig, out / "fig4_exploration_walk.png", (
        f"Fig. 4. The exploration walk (eq. 1) for alpha = {', '.join(f'{a:g}' for a in alphas)}, "
        f"beta = {float(cfg.exploration.beta):g}, P_max = {float(cfg.exploration.p_max):g} kPa, "
        f"{seconds:.0f} s at {float(cfg.robot.control_hz):g} Hz, the same random draws for "
        "each alpha, projected onto the simulated arm's safe set (valves 0 to "
        f"{float(cfg.robot.limits.p_max):g} kPa, sum at most "
        f"{min(float(cfg.robot.limits.sum_max), float(cfg.exploration.p_max)):g} kPa). "
        "Run: python -m pipeline stage=collect robot=sim robot.num_runs=1 (its "
        "figures/exploration_alphas.png). The paper's walk was not clipped at 0 kPa (its "
        "recorded valves went down to about -2.3 kPa); here every command is projected."),
        captions)

    every = np.concatenate([p[["x", "y", "z"]].to_numpy() * 1e3 for p in positions.values()])
    pad = 2.0
    limits = [(every[:, k].min() - pad, every[:, k].max() + pad) for k in range(3)]
    heights = [limits[1][1] - limits[1][0], limits[2][1] - limits[2][0]]
    width = limits[0][1] - limits[0][0]
    fig, axes = plt.subplots(2, len(alphas), squeeze=False, figsize=(
        3.2 * len(alphas), 3.2 * sum(heights) / width + 1.6), gridspec_kw={"height_ratios": heights})
    rms = {}
    for c, alpha in enumerate(alphas):
        xyz = positions[alpha][["x", "y", "z"]].to_numpy() * 1e3
        for r, (j, name) in enumerate(((1, "y"), (2, "z"))):
            ax = axes[r, c]
            ax.plot(xyz[:, 0], xyz[:, j], lw=0.3, color=f"C{c}")
            ax.plot(xyz[0, 0], xyz[0, j], "k+", ms=9)
            ax.set(xlim=limits[0], ylim=limits[j], xlabel="x [mm]")
            ax.set_aspect("equal", adjustable="box")
            if c == 0:
                ax.set_ylabel(f"{name} [mm]")
        spread = np.linalg.norm(xyz - xyz.mean(axis=0), axis=1)
        rms[alpha] = float(np.sqrt((spread ** 2).mean()))
        axes[0, c].set_title(f"alpha = {alpha:g}\nRMS spread {rms[alpha]:.1f} mm", fontsize=9)
    fig.suptitle("Tip position of the simulated arm under the exploration walk (top: x-y, "
                 "bottom: x-z; +: start)", fontsize=10)
    fig.tight_layout()
    _save(fig, out / "fig5_task_space_alphas.png", (
        "Fig. 5. Motion capture of the simulated arm (robot=sim: pure-JAX bellows arm with "
        "pressure lag, hysteresis, creep and mocap noise) driven by the walk of Fig. 4, one run "
        f"of {seconds:.0f} s per alpha. Run: python -m pipeline stage=collect robot=sim "
        "robot.num_runs=1 exploration.alpha=A for each A. RMS distance from the mean position: "
        + ", ".join(f"{rms[a]:.1f} mm at alpha {a:g}" for a in alphas) + "."), captions)


# ---------------------------------------------------------------------------------------------
# Figs. 6 and 7: the dynamics model on the real runs
# ---------------------------------------------------------------------------------------------
def model_figures(out: Path, base: tuple[str, ...], captions: dict[str, str]) -> Any:
    import matplotlib.pyplot as plt

    from pipeline.data.alignment import load_runs
    from pipeline.data.runs import runs_by_id
    from pipeline.dynamics.checkpoints import load_dynamics
    from pipeline.dynamics.figures import plot_reconstruction
    from pipeline.dynamics.scoring import LEARNED

    fits, durations = {}, {}
    for order in ("permuted", "sequential"):
        started = time.perf_counter()
        fits[order] = run_stage("fit_model", "robot=sorolex_csv", SPLIT_PROTOCOL,
                                f"dataset.order={order}", *base)
        durations[order] = time.perf_counter() - started
    cfg = compose(base, "robot=sorolex_csv", SPLIT_PROTOCOL)
    model, data = cfg.model, cfg.dataset
    cell = str(model.cell.value).upper()
    paper = reference("experiment=paper")  # the paper's model and windows

    fig, (ax_loss, ax_mm) = plt.subplots(1, 2, figsize=(11, 4))
    final = {}
    for i, (order, results) in enumerate(fits.items()):
        losses = pd.read_parquet(results["fit_model"].file("losses.parquet"))
        smooth = losses["train_loss"].ewm(alpha=EMA_WEIGHT, adjust=True).mean()
        ax_loss.semilogy(losses["step"], smooth, color=f"C{i}", lw=1.4,
                         label=f"{order}: train (EMA {EMA_WEIGHT})")
        val = losses.dropna(subset=["val_loss"])
        if val.empty:
            raise RuntimeError(f"{results['fit_model'].path}/losses.parquet has no validation rows "
                               f"(dataset.protocol={cfg.dataset.protocol}): Fig. 6 needs a split")
        ax_loss.semilogy(val["step"], val["val_loss"], "o--", color=f"C{i}", ms=4,
                         label=f"{order}: validation")
        ax_mm.plot(val["step"], val["val_mean_mm"], "o-", color=f"C{i}", ms=4, label=order)
        final[order] = (float(val["val_loss"].iloc[-1]), float(val["val_mean_mm"].iloc[-1]))
    ax_loss.set(xlabel="training step", ylabel="loss (normalized MSE)")
    ax_mm.set(xlabel="training step", ylabel="held-out open-loop error [mm] (mean)")
    ax_loss.legend(fontsize=8)
    ax_mm.legend(fontsize=8)
    fig.tight_layout()
    split = json.loads(fits["permuted"]["fit_model"].file("split.json").read_text())
    agrees = final["permuted"][0] < final["sequential"][0]
    verdict = (f"{'Agrees with' if agrees else 'DIFFERS from'} the paper ({CLAIM_FIG6}) on "
               f"this one split and training seed: final validation loss permuted "
               f"{final['permuted'][0]:.3g} vs sequential {final['sequential'][0]:.3g}, "
               f"open-loop error {final['permuted'][1]:.2f} vs {final['sequential'][1]:.2f} mm.")
    _save(fig, out / "fig6_loss_permuted_vs_sequential.png", (
        f"Fig. 6. The {cell} dynamics model fitted to the real runs ({len(split['train'])} "
        f"training runs, validation on {len(split['test'])} held-out: {', '.join(split['test'])}) "
        "with windows drawn in permuted or in sequential order; training loss smoothed by an "
        f"EMA of weight {EMA_WEIGHT}, validation over the entire held-out runs every "
        f"{int(model.eval_every)} steps. Run: python -m pipeline stage=fit_model "
        f"robot=sorolex_csv {SPLIT_PROTOCOL} dataset.order=permuted|sequential "
        f"({_seconds(durations['permuted'])} and {_seconds(durations['sequential'])} here). "
        f"Smaller than the paper: a {cell} of {int(model.hidden)} units instead of the paper's "
        f"{str(paper.model.cell.value).upper()} of {int(paper.model.hidden)}, {int(model.num_steps):,} steps instead of "
        f"{int(paper.model.num_steps):,}, at {float(data.model_hz):g} Hz with windows of "
        f"{int(data.window)} instead of {float(paper.dataset.model_hz):g} Hz and "
        f"{int(paper.dataset.window)} (the project's default model). {verdict}"), captions)

    artifact = fits["permuted"]["fit_model"]
    runs = runs_by_id(load_runs(fits["permuted"]["align"].file("aligned.parquet"),
                                float(data.model_hz), str(data.model_grid)))
    params = load_dynamics(artifact.file("model.msgpack"))
    shown = [runs[split["train"][0]]] + ([runs[split["test"][0]]] if split["test"] else [])
    png = plot_reconstruction(out / "fig7_reconstruction.raw.png", params, shown,
                              ["training run", "unseen run"])
    fig, _ = _image_figure(png, 14)
    png.unlink()
    metrics = pd.read_parquet(artifact.file("metrics.parquet"))
    learned = metrics[metrics["model"] == LEARNED].set_index("run_id")
    numbers = ", ".join(f"{rid} ({'train' if rid in split['train'] else 'held out'}) "
                        f"{learned.loc[rid, 'mean_mm']:.2f} mm mean / "
                        f"{learned.loc[rid, 'p95_mm']:.2f} "
                        "mm p95" for rid in [r.run_id for r in shown])
    _save(fig, out / "fig7_reconstruction.png", (
        "Fig. 7. Open-loop reconstruction by the permuted-order model of Fig. 6: the position "
        "predicted from the commands alone over the entire run (red) against motion capture "
        "(black), for a training run and an unseen real run, the error |predicted - measured| "
        "below, and a 30 s zoom beside each. Run: python -m pipeline stage=fit_model "
        f"robot=sorolex_csv {SPLIT_PROTOCOL}. Measured: {numbers}. The unseen run's error is what the policies "
        "meet when the model stands in for the arm."), captions)
    return fits["permuted"]


# ---------------------------------------------------------------------------------------------
# Fig. 8: PPO in the learned model of the real runs
# ---------------------------------------------------------------------------------------------
def return_figure(out: Path, base: tuple[str, ...], captions: dict[str, str], seeds: int,
                  steps: int) -> None:
    import matplotlib.pyplot as plt

    from pipeline.rl.results import RETURN_LABEL, return_curves
    from pipeline.schemas import budget_overrides, no_randomization_overrides

    fig, ax = plt.subplots(figsize=(8, 4.2))
    finals, durations, cfg = {}, {}, None
    # the paper's task: absolute pressures, the model as it is (no robustness settings)
    paper_task = ("env.action_mode=absolute", "env.ensemble_seeds=1", *no_randomization_overrides())
    for i, agent in enumerate(("ppo_ff", "ppo_rnn")):
        overrides = ("experiment=real_arm", *paper_task, f"agent={agent}",
                     f"agent.num_seeds={seeds}", *budget_overrides(steps))
        artifact = run_stage("train_ppo", *overrides, *base)["train_ppo"]
        summary = artifact.manifest["summary"]
        durations[agent] = float(summary["compile_seconds"]) + float(summary["train_seconds"])
        cfg = compose(base, *overrides)
        curves = return_curves(pd.read_parquet(artifact.file("metrics.parquet")))
        if curves.empty:
            raise SystemExit(f"Fig. 8: no training episode of {agent} ended within "
                             f"--ppo-steps={steps} (episodes last {int(cfg.env.max_steps)} "
                             "periods): give it more steps")
        stats = curves.groupby("timesteps")["return"].agg(["mean", "std"]).reset_index()
        ax.plot(stats["timesteps"], stats["mean"], color=f"C{i}",
                label=f"{agent} ({curves['seed'].nunique()} seeds)")
        ax.fill_between(stats["timesteps"], stats["mean"] - stats["std"],
                        stats["mean"] + stats["std"], color=f"C{i}", alpha=0.25)
        last = curves[curves["timesteps"] == curves["timesteps"].max()]["return"]
        finals[agent] = (float(last.mean()), float(last.std()), len(last))
    cell = str(cfg.model.cell.value).upper()
    ax.set(xlabel="environment steps per seed", title=f"PPO in the {cell} fitted to the real runs")
    ax.set_ylabel(RETURN_LABEL)
    ax.legend(fontsize=8)
    fig.tight_layout()
    (ff, ff_std, n_ff), (rnn, rnn_std, n_rnn) = finals["ppo_ff"], finals["ppo_rnn"]
    standard_error = np.sqrt(ff_std ** 2 / n_ff + rnn_std ** 2 / n_rnn)
    if abs(ff - rnn) <= 2 * standard_error:
        comparison = "no difference beyond two standard errors over seeds at this budget"
    else:
        comparison = f"{'ppo_ff' if ff > rnn else 'ppo_rnn'} ahead by more than two standard " \
                     "errors over seeds at this budget"
    full = reference("experiment=real_arm").agent  # the experiment as configured
    budget = f"{int(full.total_timesteps):,}"
    if full.recurrent_total_timesteps is not None:
        budget += f" (ppo_rnn {int(full.recurrent_total_timesteps):,})"
    shrunk = [f"{steps:,} steps per seed instead of {budget}"]
    if seeds != int(full.num_seeds):
        shrunk.append(f"{seeds} seeds instead of {int(full.num_seeds)}")
    _save(fig, out / "fig8_returns_ff_vs_rnn.png", (
        "Fig. 8. Episodic return during PPO training of the feed-forward (ppo_ff) and the "
        f"recurrent GRU (ppo_rnn) policy in the learned environment of the real runs (the {cell} "
        "fitted to all of them, as experiment=real_arm trains in), mean ± one std over seeds; the return of an update "
        "is the mean over the training episodes that ended in it, the first updates (no episode "
        f"could yet have lasted {int(cfg.env.max_steps)} periods) left out. Run: python -m "
        f"pipeline stage=train_ppo experiment=real_arm {' '.join(paper_task)} agent=ppo_ff|ppo_rnn "
        f"agent.num_seeds={seeds} agent.total_timesteps={steps} ({durations['ppo_ff']:.0f} s and "
        f"{durations['ppo_rnn']:.0f} s of compilation and training). Shrunk to run in minutes: "
        f"{'; '.join(shrunk)}. Return of the last update: ppo_ff {ff:.1f} ± {ff_std:.1f}, "
        f"ppo_rnn {rnn:.1f} ± {rnn_std:.1f} (mean ± std over seeds): {comparison}."), captions)


# ---------------------------------------------------------------------------------------------
# Tracking: the policies that follow moving references, from an existing evaluation
# ---------------------------------------------------------------------------------------------
TRACKING = ("experiment=tracking",)


def tracking_figure(out: Path, base: tuple[str, ...], captions: dict[str, str],
                    settings: tuple[str, ...] = TRACKING) -> Path | None:
    """The tracking figure from the evaluate artifact of the config of ``settings``
    (overrides), or None (logged) where that evaluation has not run."""
    from pipeline import keys
    from pipeline.evaluation.tracking_report import PLANT_LABELS, draw_tracking
    from pipeline.infra.artifacts import ArtifactStore

    cfg = compose(base, *settings)
    artifact = ArtifactStore(cfg.paths.artifact_dir).find("evaluate", keys.key("evaluate", cfg))
    command = " ".join(["python -m pipeline", *(shlex.quote(s) for s in settings)])
    if artifact is None or not artifact.file("tracking_paths.parquet").is_file():
        log.info("tracking figure skipped: no tracking evaluation of this config (%s makes it)",
                 command)
        return None
    paths = pd.read_parquet(artifact.file("tracking_paths.parquet"))
    summary = pd.read_parquet(artifact.file("tracking.parquet"))
    plant = "plant" if "plant" in set(paths["plant"]) else "learned"
    settle = float(cfg.evaluation.tracking_settle_seconds)
    fig = draw_tracking(paths, plants=[plant], spread=True, since_s=settle)
    horizon = cfg.evaluation.tracking_mpc_horizon
    horizon = (f"{int(horizon)} control period{'s' if int(horizon) > 1 else ''}"
               if horizon is not None else "the policies' preview")
    shown = summary[(summary["plant"] == plant) & (summary["controller"] != "preload")]
    rmse = "; ".join(
        f"{name}: " + ", ".join(f"{row.controller} {row.median_rmse_mm:.2f}"
                                for row in part.itertuples())
        for name, part in shown.groupby("reference", sort=False))
    episodes, seeds = int(paths["episode"].nunique()), int(paths["seed"].nunique())
    return _save(fig, out / "tracking_paths_and_error.png", (
        f"Tracking on the {PLANT_LABELS.get(plant, plant)}: each reference (grey; "
        f"{float(cfg.evaluation.tracking_seconds):g} s from the arm at rest) against the path of "
        "each tracking policy (seed 0, episode 0) and of the baselines (mpc: sampling MPC on the "
        f"learned model scored against the reference over {horizon}; '(reaching)': the "
        "reaching policies fed the moving goal), left in x-z from the first "
        f"{settle:g} s on, right the distance to the reference over time from the start, the "
        f"median and quartiles over the first {episodes} episodes (phases spread over a lap) "
        f"and the seeds ({seeds} of each policy). Run: {command} (its evaluate artifact "
        f"{artifact.path.name}). Median RMSE [mm] after the first {settle:g} s over "
        f"{int(cfg.evaluation.num_episodes)} episodes and every seed: {rmse}."), captions)


def main(argv: list[str] | None = None) -> None:
    from pipeline.config import PROJECT_ROOT

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=PROJECT_ROOT / "outputs" / "paper_figures",
                        help="where the figures and captions.md go")
    parser.add_argument("--output-dir", type=Path, default=PROJECT_ROOT / "outputs",
                        help="the pipeline's paths.output_dir (its artifacts are reused)")
    parser.add_argument("--seeds", type=int, default=20, help="PPO seeds per policy type")
    parser.add_argument("--ppo-steps", type=int, default=102_400,
                        help="PPO environment steps per seed")
    parser.add_argument("--only", nargs="*", default=["4", "5", "6", "7", "8", "tracking"],
                        help="figures to make (4 and 5 go together, 6 and 7 too)")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", dest="settings",
                        help="Hydra overrides for every stage run (e.g. model.num_steps=50)")
    parser.add_argument("--tracking-set", nargs="*", default=list(TRACKING),
                        metavar="KEY=VALUE",
                        help="the overrides of the tracking evaluation the tracking figure is "
                             "drawn from (default: experiment=tracking)")
    args = parser.parse_args(argv)
    base = base_overrides(args.output_dir, tuple(args.settings))
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s][%(name)s] %(message)s")
    args.out.mkdir(parents=True, exist_ok=True)
    captions: dict[str, str] = {}
    if {"4", "5"} & set(args.only):
        exploration_figures(args.out, base, captions)
    if {"6", "7"} & set(args.only):
        model_figures(args.out, base, captions)
    if "8" in args.only:
        return_figure(args.out, base, captions, args.seeds, args.ppo_steps)
    if "tracking" in args.only:
        tracking_figure(args.out, base, captions, tuple(args.tracking_set))
    text = ["# The paper's figures, from this project's artifacts", ""]
    text += [f"![{name}]({name})\n\n{caption}\n" for name, caption in sorted(captions.items())]
    (args.out / "captions.md").write_text("\n".join(text))
    log.info("figures and captions.md in %s", args.out)


if __name__ == "__main__":
    main()
