"""Stage ``calibrate``: the simulated arm's physics fitted to the aligned runs.

The aligned runs (any robot: the paper's CSVs, PlotJuggler exports, rosbags, a ROS 2 collection,
or the simulated arm itself) are resampled to ``calibration.rate_hz``, each from
``calibration.start_s`` s on (e.g. after an opening hold over which the arm still settles), and
each is driven open loop through the simulator with its own pressure commands, started settled at
the first of them; the physics (``calibration.fitted``, bounded, see
:mod:`pipeline.arm.calibration`) and one rest offset per
training run are fitted by Adam, from ``calibration.num_restarts`` starts, all in one program.
With ``calibration.leave_one_run_out`` every run is also held out once and its open-loop error is
scored at ``dataset.model_hz``, in fit_model's table format, next to the hand-set simulator and
fit_model's baselines (mean position, linear lagged pressures) trained on the same runs:
``sim_calibrated`` rests where the training runs rest (the mean of their fitted offsets: nothing
of the held-out run is used), ``sim_calibrated_first_pose`` rests on the held-out run's first
recorded pose (the learned model's protocol); ``sim_default`` is the hand-set simulator at its
own rest pose, ``sim_default_first_pose`` on the first pose.

Artifact: ``physics.json`` (the SimPhysics values of the fit on all runs, the base position and
rest-pose spread from its offsets: what ``robot.physics_from`` reads; one physics for every run,
so ``session_std`` is neither fitted nor written and ``physics_from`` leaves it as configured), ``parameters.parquet`` and
``parameters.md`` (value, unit, bounds and start of every fitted parameter, per fold), per-run
``offsets.parquet``, ``robot_sim.yaml`` (a ``conf/robot`` file holding the fitted physics),
``metrics.parquet`` (per run and split: mean and p95 open-loop error in mm),
``losses.parquet`` and ``figures/reconstruction.png``.
"""

from __future__ import annotations

import json
import logging
from typing import Any

from pipeline import keys
from pipeline.arm import calibration as calib
from pipeline.data.alignment import runs_at_model_rate
from pipeline.data.runs import Run
from pipeline.data.schemas import ALIGNED, DataError, read_table, write_table
from pipeline.dynamics import calibration_report as report
from pipeline.infra.artifacts import Artifact, ArtifactStore, produce
from pipeline.infra.parquet import table_metadata, write_parquet
from pipeline.schemas import ConfigError

log = logging.getLogger(__name__)
STAGE = "calibrate"


def calibrate(cfg: Any) -> Artifact:
    store = ArtifactStore(cfg.paths.artifact_dir)
    spec, inputs = keys.calibrate_spec(cfg)
    aligned_artifact = store.require("align", inputs["align"])
    settings = cfg.calibration
    rate_hz, model_hz = float(settings.rate_hz), float(cfg.dataset.model_hz)
    stride = round(rate_hz / model_hz)
    if stride < 1 or abs(stride * model_hz - rate_hz) > 1e-6:
        raise ValueError(f"calibration.rate_hz={rate_hz} must be a whole multiple of "
                         f"dataset.model_hz={model_hz} (errors are scored at model_hz)")

    start_s = float(settings.start_s)
    if not start_s >= 0.0:
        raise ConfigError(f"calibration.start_s={settings.start_s} must be 0 or more (s into "
                          "each run)")

    def build(writer):
        aligned, _ = read_table(aligned_artifact.file("aligned.parquet"), ALIGNED)
        runs, model_runs = (_from_start(runs_at_model_rate(aligned, hz, "clock"), start_s,
                                        aligned_artifact.file("aligned.parquet"))
                            for hz in (rate_hz, model_hz))
        log.info("calibrate: %d runs at %.3g Hz from %g s on (%d frames max), %d parameters, "
                 "%s x %d restarts x %d steps", len(runs), rate_hz, start_s,
                 max(len(r) for r in runs), len(list(settings.fitted)),
                 f"{len(runs) + 1} fits" if settings.leave_one_run_out else "1 fit",
                 int(settings.num_restarts), int(settings.num_steps))
        fit = report.fit_runs(runs, settings)
        predicted, metrics = report.scored(fit, runs, model_runs, stride)
        config = {"calibration": spec["calibration"], "robot": cfg.robot.name}
        write_outputs(writer, config, {"stage": STAGE, "inputs": inputs}, fit, runs, metrics,
                      predicted)

    return produce(store, STAGE, spec, inputs, build, force=cfg.force)


def _from_start(runs: list[Run], start_s: float, source: Any) -> list[Run]:
    """Each run from ``start_s`` s on; a :class:`DataError` naming the run that ends before."""
    try:
        return [run.after(start_s) for run in runs]
    except ValueError as err:
        raise DataError(source, f"calibration.start_s={start_s:g}: {err}") from err


def write_outputs(writer, config, provenance, fit: report.Fit, runs, metrics, predicted
                  ) -> None:
    folds, param, init, result = fit.folds, fit.param, fit.init, fit.result
    run_ids = [r.run_id for r in runs]
    fold_names = [f if f == report.ALL_RUNS else runs[f].run_id for f in folds]
    fitted = fit.physics()
    writer.file("physics.json").write_text(json.dumps(
        {"physics": fitted, "units": {k: calib.UNITS.get(k, "") for k in fitted},
         "runs": run_ids}, indent=2))
    writer.file("robot_sim.yaml").write_text(report.robot_yaml(fitted, run_ids))

    parameters = report.parameter_table(fold_names, param, result, init)
    write_table(parameters, writer.file("parameters.parquet"), report.PARAMETERS, config,
                provenance)
    writer.file("parameters.md").write_text(report.parameter_markdown(
        parameters[parameters["fold"] == report.ALL_RUNS]))
    write_table(report.offsets_table(runs, result), writer.file("offsets.parquet"),
                report.OFFSETS, config, provenance)
    write_parquet(metrics, writer.file("metrics.parquet"), table_metadata(
        metrics, "calibration_metrics", config, provenance, {"steps": "model steps"}))
    losses = report.losses_table(result, fold_names)
    write_parquet(losses, writer.file("losses.parquet"), table_metadata(
        losses, "calibration_losses", config, provenance,
        {"loss_mm2": "mm^2", "step": "Adam step"}))
    report.plot_reconstruction(writer.file("figures/reconstruction.png"), runs, folds,
                               predicted["sim_calibrated"], predicted["sim_default"][0])

    summary = report.summary(runs, param, result, metrics)
    writer.summary = summary
    held = "test" if "test_sim_calibrated_mean_mm" in summary else "train"
    log.info("calibrate: %s open-loop error %.2f mm mean, %.2f mm p95 (from the first pose %.2f "
             "mm; hand-set simulator %.2f mm, mean position %.2f mm, linear lagged %.2f mm)",
             "leave-one-run-out" if held == "test" else "in-sample",
             summary[f"{held}_sim_calibrated_mean_mm"], summary[f"{held}_sim_calibrated_p95_mm"],
             summary[f"{held}_sim_calibrated_first_pose_mean_mm"],
             summary[f"{held}_sim_default_mean_mm"], summary[f"{held}_mean_position_mean_mm"],
             summary[f"{held}_linear_lagged_mean_mm"])
