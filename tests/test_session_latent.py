"""The learned session latent: a latent model at z = 0 is the plain model; trained on runs that
differ by a known gain, the latent inferred from a context brings the rest of a new run closer."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pipeline.data.runs import Run
from pipeline.dynamics import adaptation, checkpoints
from pipeline.dynamics import cv as model_cv
from pipeline.dynamics import model as dynamics
from pipeline.dynamics.scoring import position_errors_mm
from pipeline.dynamics.session_latent import (
    SessionLatentSettings,
    infer_latent,
    training_latents,
)


def tiny_params(dim=3, num_runs=4):
    config = dynamics.DynamicsConfig(hidden=8, cell="gru")
    ones, zeros = jnp.ones(3), jnp.zeros(3)
    normalizer = dynamics.Normalizer(zeros, 10 * ones, zeros, 0.01 * ones, zeros, 0.01 * ones)
    plain = dynamics.DynamicsParams(network=dynamics.init_network(jax.random.PRNGKey(0), config),
                                    normalizer=normalizer, config=config)
    return plain, dynamics.init_session(jax.random.PRNGKey(1), plain, num_runs, dim)


def test_zero_latent_is_the_plain_model():
    plain, latent = tiny_params()
    pressures = jnp.asarray(np.random.default_rng(0).uniform(0, 30, (25, 3)), jnp.float32)
    pose = jnp.asarray([0.01, 0.3, 0.2])
    expected = dynamics.predict_sequence(plain, pressures, pose)
    assert dynamics.session_latent_dim(plain) == 0 and dynamics.session_latent_dim(latent) == 3
    np.testing.assert_array_equal(
        dynamics.predict_sequence(latent, pressures, pose, latent=jnp.zeros(3)), expected)
    np.testing.assert_array_equal(dynamics.predict_sequence(latent, pressures, pose), expected)
    _, stepped = jax.lax.scan(lambda c, p: dynamics.step(latent, c, p),
                              dynamics.init_carry(latent, pose), pressures)
    np.testing.assert_allclose(stepped, expected, atol=1e-7)
    moved = dynamics.predict_sequence(latent, pressures, pose, latent=jnp.asarray([1.0, 0, 0]))
    assert float(jnp.max(jnp.abs(moved - expected))) > 1e-5  # the latent does change it


def test_gate_bias_is_the_latent_times_the_map():
    """z = (1, -2), G[0] all 0.5, G[1] all 0.25: every gate bias is 0.5 - 0.5 = 0; z = (2, 0):
    1.0 everywhere."""
    _, latent = tiny_params(dim=2)
    gate_map = jnp.stack([jnp.full((3, 8), 0.5), jnp.full((3, 8), 0.25)])
    latent = latent.replace(network={**latent.network, dynamics.SESSION: {
        "gate_map": gate_map, "latents": jnp.zeros((4, 2))}})
    np.testing.assert_allclose(dynamics.session_gate_bias(latent, jnp.asarray([1.0, -2.0])), 0.0)
    np.testing.assert_allclose(dynamics.session_gate_bias(latent, jnp.asarray([2.0, 0.0])), 1.0)
    with pytest.raises(ValueError, match="dim"):
        dynamics.init_session(jax.random.PRNGKey(0), latent, 4, 0)


def test_session_latent_round_trips_through_the_model_file(tmp_path):
    _, latent = tiny_params()
    latent = latent.replace(network={**latent.network, dynamics.SESSION: {
        **latent.network[dynamics.SESSION], "latents": jnp.arange(12.0).reshape(4, 3)}})
    checkpoints.save_dynamics(tmp_path / "m.msgpack", latent)
    loaded = checkpoints.load_dynamics(tmp_path / "m.msgpack")
    np.testing.assert_array_equal(training_latents(loaded), np.arange(12.0).reshape(4, 3))
    pressures = jnp.ones((5, 3))
    z = jnp.asarray([0.3, -0.1, 0.2])
    np.testing.assert_array_equal(
        dynamics.predict_sequence(loaded, pressures, jnp.zeros(3), latent=z),
        dynamics.predict_sequence(latent, pressures, jnp.zeros(3), latent=z))


def test_settings_and_mechanism_checks():
    with pytest.raises(ValueError, match="dim"):
        SessionLatentSettings(dim=0)
    with pytest.raises(ValueError, match="prior"):
        SessionLatentSettings(prior=-1.0)
    with pytest.raises(ValueError, match="latent_prior"):
        adaptation.AdaptationSettings(mechanism="latent", latent_prior=-1.0)
    plain, latent = tiny_params()
    context = np.ones((10, 3), np.float32), np.zeros((10, 3), np.float32)
    with pytest.raises(ValueError, match="session latents"):
        adaptation.adapt(plain, *context, adaptation.AdaptationSettings(mechanism="latent"), 10.0)
    identity = adaptation.adapt(latent, context[0][:0], context[1][:0],
                                adaptation.AdaptationSettings(mechanism="latent"), 10.0)
    assert identity.latent is None  # no context: z = 0, the model without session


def gain_runs(gains, num_steps=240, seed=0):
    """Runs of one first-order arm (pole 0.7) whose commands act through ``gain`` times a fixed
    map: the session differs by a known gain."""
    rng = np.random.default_rng(seed)
    base = np.array([[2.0, -1.0, 0.0], [0.5, 0.5, 0.5], [0.0, 1.0, -2.0]]) * 1e-3
    runs = []
    for i, gain in enumerate(gains):
        commands = rng.uniform(0.0, 5.0, (num_steps // 6 + 1, 3))
        pressure = np.repeat(commands, 6, axis=0)[:num_steps]
        position, state = [], np.zeros(3)
        for p in pressure:
            state = 0.7 * state + 0.3 * gain * base @ p
            position.append(np.array([0.03, 0.35, 0.2]) + state)
        runs.append(Run(f"run{i}", np.arange(num_steps) / 10.0, pressure.astype(np.float32),
                        np.asarray(position, np.float32)))
    return runs


@pytest.mark.slow
def test_inferred_latent_recovers_a_sessions_gain():
    """Trained on runs of gain 0.5, 0.8, 1.2, 1.5 with a 2-d latent, the model given the first
    12 s of a run of gain 1.4 predicts its last 12 s closer (by a fifth at least) than with z = 0; the learned
    latents order the training runs by gain along some direction (distinct rows)."""
    runs = gain_runs([0.5, 0.8, 1.2, 1.5, 1.4])
    members = [model_cv.Member(tuple(r.run_id for r in runs[:4]), runs[4].run_id, 0)]
    config = {"hidden": 16, "head": [], "batch_size": 16, "learning_rate": 1e-2,
              "lr_schedule": "constant", "num_steps": 400, "checkpoint_every": 400,
              "recurrent_dropout": 0.0, "predict_displacement": True}
    (params,), _ = model_cv.fit_members(runs, members, config, window=30, progress=False,
                                        latent=SessionLatentSettings(dim=2, prior=1e-3))
    table = np.asarray(training_latents(params))
    np.testing.assert_array_equal(table[4], 0.0)  # the held-out run's row is never trained
    assert np.min(np.linalg.norm(table[:4, None] - table[None, :4], axis=-1)
                  + np.eye(4)) > 1e-3
    held = runs[4]
    context = 120
    z = infer_latent(params, jnp.asarray(held.pressures_kpa[:context]),
                     jnp.asarray(held.positions_m[:context]), 300, 0.05, 1e-3)

    def rest_error(latent):
        predicted = dynamics.predict_sequence(params, jnp.asarray(held.pressures_kpa),
                                              jnp.asarray(held.positions_m[0]), latent=latent)
        return position_errors_mm(np.asarray(predicted)[context:],
                                  held.positions_m[context:])["mean_mm"]

    without, inferred = rest_error(None), rest_error(z)
    assert inferred < 0.8 * without, (inferred, without)


def test_latent_without_context_is_the_training_mean_when_centred_there():
    """Learned latents (1, 1), (3, 3) and an untrained row (0, 0): the trained rows' mean is
    (2, 2), the latent without context; the zero centre leaves the model without session."""
    _, latent = tiny_params(dim=2, num_runs=3)
    session = {**latent.network[dynamics.SESSION],
               "latents": jnp.asarray([[1.0, 1.0], [0.0, 0.0], [3.0, 3.0]])}
    latent = latent.replace(network={**latent.network, dynamics.SESSION: session})
    np.testing.assert_array_equal(training_latents(latent, trained_only=True),
                                  [[1.0, 1.0], [3.0, 3.0]])
    empty = np.zeros((0, 3), np.float32)
    centred = adaptation.adapt(latent, empty, empty, adaptation.AdaptationSettings(
        mechanism="latent", latent_center="training_mean"), 10.0)
    np.testing.assert_allclose(centred.latent, [2.0, 2.0])
    with pytest.raises(ValueError, match="latent_center"):
        adaptation.AdaptationSettings(mechanism="latent", latent_center="median")
