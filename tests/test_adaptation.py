"""Calibrating the forward model to a session's context (pipeline/dynamics/adaptation.py)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pipeline.data.runs import Run
from pipeline.dynamics import adaptation
from pipeline.dynamics import model as dynamics
from pipeline.dynamics.adaptation import AdaptationSettings, SessionCorrection
from pipeline.dynamics.model import DynamicsConfig, DynamicsParams

CONFIG = DynamicsConfig(hidden=4, cell="gru", step_size=True, step_decays=(3.0,))
HZ = 10.0


def tiny_model() -> tuple[DynamicsParams, Run]:
    """A random 4-unit GRU and a 60-step run of held random commands (positions unused)."""
    rng = np.random.default_rng(0)
    pressure = np.repeat(rng.uniform(0.0, 5.0, (12, 3)), 5, axis=0).astype(np.float32)
    position = (0.03 + 0.01 * rng.normal(size=(60, 3))).astype(np.float32)
    run = Run("r", np.arange(60) / HZ, pressure, position)
    params = DynamicsParams(network=dynamics.init_network(jax.random.PRNGKey(1), CONFIG),
                            normalizer=dynamics.fit_normalizer([run], False), config=CONFIG)
    return params, run


def plain(params, run):
    return np.asarray(dynamics.predict_sequence(params, jnp.asarray(run.pressures_kpa),
                                                jnp.asarray(run.positions_m[0])))


def rest_error_mm(params, correction, run, observed, start):
    predicted = adaptation.predict_adapted(params, correction, jnp.asarray(run.pressures_kpa),
                                           jnp.asarray(observed[0]))
    return 1000.0 * np.abs(np.asarray(predicted)[start:] - observed[start:]).max()


# latent needs a model trained with session latents: tests/test_session_latent.py
@pytest.mark.parametrize("mechanism, readout", [(m, False) for m in adaptation.MECHANISMS
                                                if m != "latent"] + [("fine_tune", True)])
def test_zero_context_is_the_plain_prediction(mechanism, readout):
    params, run = tiny_model()
    settings = AdaptationSettings(mechanism=mechanism, steps=5, readout=readout)
    correction = adaptation.adapt(params, run.pressures_kpa[:0], run.positions_m[:0], settings,
                                  HZ)
    predicted = adaptation.predict_adapted(params, correction, jnp.asarray(run.pressures_kpa),
                                           jnp.asarray(run.positions_m[0]))
    np.testing.assert_array_equal(np.asarray(predicted), plain(params, run))


def test_offset_recovers_a_shifted_session_exactly():
    params, run = tiny_model()
    shift = np.array([0.002, -0.001, 0.003], np.float32)  # 2, -1, 3 mm
    observed = plain(params, run) + shift
    settings = AdaptationSettings(mechanism="offset")
    correction = adaptation.adapt(params, run.pressures_kpa[:20], observed[:20], settings, HZ)
    np.testing.assert_allclose(correction.output_offset_m, shift, atol=1e-6)
    assert rest_error_mm(params, SessionCorrection.identity(), run, observed, 20) > 2.9
    assert rest_error_mm(params, correction, run, observed, 20) < 1e-3
    # the offset over the last second of the context only: the same shift
    last = adaptation.adapt(params, run.pressures_kpa[:20], observed[:20],
                            AdaptationSettings(mechanism="offset", offset_window_s=1.0), HZ)
    np.testing.assert_allclose(last.output_offset_m, shift, atol=1e-6)


def test_fine_tune_recovers_an_affine_map_of_the_prediction():
    params, run = tiny_model()
    raw = plain(params, run)
    center = raw[:30].mean(0)
    gain = np.array([0.3, -0.2, 0.25], np.float32)
    shift = np.array([0.002, -0.001, 0.003], np.float32)
    observed = center + (raw - center) * (1.0 + gain) + shift
    before = rest_error_mm(params, SessionCorrection.identity(), run, observed, 30)
    settings = AdaptationSettings(mechanism="fine_tune", output="diagonal", input_affine=False,
                                  steps=400, learning_rate=0.05, prior_mm2=0.0)
    correction = adaptation.adapt(params, run.pressures_kpa[:30], observed[:30], settings, HZ)
    np.testing.assert_allclose(np.diag(correction.output_matrix), gain, atol=0.02)
    after = rest_error_mm(params, correction, run, observed, 30)
    assert before > 3.0 and after < 0.05 * before, (before, after)


def test_readout_fine_tune_fits_the_context_and_keeps_the_model():
    params, run = tiny_model()
    observed = plain(params, run) * 1.1 - 0.003
    settings = AdaptationSettings(mechanism="fine_tune", output="bias", input_affine=False,
                                  readout=True, steps=300, learning_rate=0.02, prior_mm2=0.0)
    correction = adaptation.adapt(params, run.pressures_kpa[:40], observed[:40], settings, HZ)
    assert correction.readout_delta["kernel"].shape == (4, 3)
    before = rest_error_mm(params, SessionCorrection.identity(), run, observed, 40)
    after = rest_error_mm(params, correction, run, observed, 40)
    assert after < 0.2 * before, (before, after)
    np.testing.assert_array_equal(params.network["params"]["readout"]["bias"],
                                  tiny_model()[0].network["params"]["readout"]["bias"])


def test_fine_tune_recovers_an_input_gain():
    params, run = tiny_model()
    scaled = run.replace(pressures_kpa=(1.2 * run.pressures_kpa + 0.3).astype(np.float32))
    observed = plain(params, scaled)
    settings = AdaptationSettings(mechanism="fine_tune", output="bias", input_affine=True,
                                  steps=400, learning_rate=0.05, prior_mm2=0.0)
    correction = adaptation.adapt(params, run.pressures_kpa[:40], observed[:40], settings, HZ)
    before = rest_error_mm(params, SessionCorrection.identity(), run, observed, 40)
    after = rest_error_mm(params, correction, run, observed, 40)
    assert after < 0.2 * before, (before, after)


@pytest.mark.parametrize("change, message", [
    ({"mechanism": "encoder"}, "mechanism must be one of"),
    ({"latent_prior": -1.0}, "latent_prior must be >= 0"),
    ({"output": "affine"}, "output must be one of"),
    ({"offset_window_s": 0.0}, "offset_window_s must be > 0"),
    ({"steps": -1}, "steps must be an integer >= 0"),
    ({"steps": 2.5}, "steps must be an integer >= 0"),
    ({"learning_rate": 0.0}, "learning_rate must be > 0"),
    ({"prior_mm2": -1.0}, "prior_mm2 must be >= 0"),
])
def test_settings_are_validated(change, message):
    with pytest.raises(ValueError, match=message):
        AdaptationSettings(**change)


def test_context_steps():
    assert adaptation.context_steps(30.0, 10.0) == 300
    assert adaptation.context_steps(0.0, 10.0) == 0
    with pytest.raises(ValueError, match="context length must be >= 0 s"):
        adaptation.context_steps(-1.0, 10.0)


def test_linear_refit_by_hand():
    features = np.array([[1.0], [2.0]])
    positions = np.array([[3.0, 0.0, 6.0], [6.0, 0.0, 12.0]])
    prior = np.zeros((1, 3))
    # w = 0.5 * (1 + 4) / 1; argmin (b - 3)^2 + (2b - 6)^2 + 2.5 b^2  ->  b = 15 / 7.5 (axis 0)
    refit = adaptation.refit_linear_on_context(prior, features, positions, ridge=0.5)
    np.testing.assert_allclose(refit, [[2.0, 0.0, 4.0]])
    # a prior of 1: argmin (b - 3)^2 + (2b - 6)^2 + 2.5 (b - 1)^2  ->  b = 17.5 / 7.5
    refit = adaptation.refit_linear_on_context(np.ones((1, 3)), features, positions, ridge=0.5)
    np.testing.assert_allclose(refit[0, 0], 17.5 / 7.5)
    np.testing.assert_array_equal(
        adaptation.refit_linear_on_context(prior, features[:0], positions[:0], 0.5), prior)
    with pytest.raises(ValueError, match="ridge must be > 0"):
        adaptation.refit_linear_on_context(prior, features, positions, 0.0)


def test_offset_on_context_by_hand():
    predicted = np.zeros((4, 3))
    positions = np.array([[1.0, 0.0, 0.0], [3.0, 2.0, 0.0]])
    np.testing.assert_allclose(adaptation.offset_on_context(predicted, positions)[3], [2, 1, 0])
    np.testing.assert_array_equal(adaptation.offset_on_context(predicted, positions[:0]),
                                  predicted)


def test_context_curve_rows():
    params, run = tiny_model()
    shift = np.array([0.002, -0.001, 0.003], np.float32)
    session = run.replace(run_id="held", positions_m=plain(params, run) + shift)
    others = [run.replace(run_id="a"), run.replace(run_id="b", pressures_kpa=run.pressures_kpa[::-1]
                                                    .copy())]
    curve = adaptation.context_curve([session], [others], [params],
                                     AdaptationSettings(mechanism="offset"), HZ,
                                     contexts_s=(0.0, 1.0, 4.0, 6.0), scored_from_s=3.0)
    # 6 s leaves no step of the 60-step run: skipped; 4 s scores from 4 s, the others from 3 s
    assert list(curve["context_s"]) == [0.0, 0.0, 1.0, 1.0, 4.0, 4.0]
    assert list(curve["from_s"]) == [3.0, 3.0, 3.0, 3.0, 4.0, 4.0]
    learned = curve[curve["model"] == "learned"].set_index("context_s")
    # no context: the plain model, off by the shift everywhere (|shift| = sqrt(14) mm)
    assert learned.loc[0.0, "mean_mm"] == pytest.approx(np.sqrt(14.0), rel=1e-4)
    assert learned.loc[1.0, "mean_mm"] < 1e-3 and learned.loc[4.0, "p95_mm"] < 1e-3
    from pipeline.dynamics.scoring import position_errors_mm, predict_linear_lagged
    linear = curve[(curve["model"] == "linear_lagged") & (curve["context_s"] == 0.0)]
    expected = position_errors_mm(predict_linear_lagged(others, session)[30:],
                                  session.positions_m[30:])
    assert linear["mean_mm"].item() == pytest.approx(expected["mean_mm"])


def test_context_metrics_are_model_metrics_rows(tmp_path):
    from pipeline.data.schemas import MODEL_METRICS, read_table, write_table
    from pipeline.dynamics.cv import Member

    params, run = tiny_model()
    runs = [run.replace(run_id="a"), run.replace(run_id="b", positions_m=plain(params, run))]
    members = [Member(("b",), "a", 3), Member(("a",), "b", 3), Member(("a", "b"), None, 3)]
    # the context curve at its defaults needs more than 60 s: 90 s runs at 1 Hz (90 steps)
    long = [r.replace(times_s=np.arange(90.0), pressures_kpa=np.tile(r.pressures_kpa, (2, 1))[:90],
                      positions_m=np.tile(r.positions_m, (2, 1))[:90]) for r in runs]
    rows = adaptation.context_metrics(long, members, [params] * 3,
                                      AdaptationSettings(mechanism="offset"), 1.0)
    assert len(rows) == 2 * len(adaptation.CONTEXTS_S) * 2
    assert set(rows["split"]) == {"cv_context"} and set(rows["from_s"]) == {60.0}
    assert list(rows.loc[rows["held_out"] == "b", "fold"].unique()) == [1]
    write_table(rows, tmp_path / "m.parquet", MODEL_METRICS)  # the schema takes them
    table, _ = read_table(tmp_path / "m.parquet", MODEL_METRICS)
    summary = adaptation.context_summary(table)
    assert list(summary["context_s"]) == list(adaptation.CONTEXTS_S)
    assert (summary["runs"] == 2).all()
    at_zero = rows[(rows["context_s"] == 0.0) & (rows["model"] == "learned")]["mean_mm"].mean()
    assert summary.loc[0, "learned_mean_mm"] == pytest.approx(at_zero)


@pytest.mark.slow
def test_fit_model_cv_on_the_recorded_runs_carries_the_context_curve(make_cfg, sorolex_dir):
    from pipeline.__main__ import run as run_pipeline
    from pipeline.data.schemas import MODEL_METRICS, read_table

    cfg = make_cfg("stage=fit_model", "robot=sorolex_csv", f"robot.data_dir={sorolex_dir}",
                   "model.hidden=8", "model.num_steps=4", "model.checkpoint_every=2",
                   "dataset.window=16")
    artifact = run_pipeline(cfg)["fit_model"]
    metrics, _ = read_table(artifact.file("metrics.parquet"), MODEL_METRICS)
    context = metrics[metrics["split"] == "cv_context"]
    # 7 held-out runs, all longer than 60 s: every context length, the model and the linear model
    assert len(context) == 7 * len(adaptation.CONTEXTS_S) * 2
    assert set(context["from_s"]) == {60.0} and (context["run_id"] == context["held_out"]).all()
    others = metrics[metrics["split"] != "cv_context"]
    assert set(others["context_s"]) == {0.0} and set(others["from_s"]) == {0.0}
    assert set(artifact.manifest["summary"]["session_context_mm"]) == {"0", "10", "30", "60"}
    # the closing summary reads the same manifest summary: the curve is not taken for a model
    from pipeline.evaluation.summary import model_table

    assert model_table(artifact.manifest["summary"])["model"].iloc[0] == "learned"
