import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pipeline.data.runs import Run
from pipeline.dynamics import model as dynamics
from pipeline.dynamics.model import DynamicsConfig, DynamicsParams

predict_sequence = jax.jit(dynamics.predict_sequence)  # one compilation per architecture


def make_runs(num_runs=2, num_steps=40, seed=0):
    rng = np.random.default_rng(seed)
    runs = []
    for i in range(num_runs):
        pressure = rng.uniform(0.0, 5.0, (num_steps, 3)).astype(np.float32)
        position = (0.03 + 0.002 * np.cumsum(rng.normal(size=(num_steps, 3)), 0)).astype(
            np.float32
        )
        runs.append(Run(f"r{i}", np.arange(num_steps) / 10.0, pressure, position))
    return runs


def make_params(config: DynamicsConfig, seed=0) -> DynamicsParams:
    runs = make_runs()
    return DynamicsParams(
        network=dynamics.init_network(jax.random.PRNGKey(seed), config),
        normalizer=dynamics.fit_normalizer(runs, config.predict_displacement),
        config=config,
    )


PLAIN_LSTM = {"cell": "lstm", "pressure_transients": ()}  # the paper's inputs
CONFIGS = [
    DynamicsConfig(hidden=8, layers=1, head=(), condition_on_initial_pose=True,
                   predict_displacement=True, **PLAIN_LSTM),
    DynamicsConfig(hidden=8, layers=2, head=(6,), condition_on_initial_pose=False,
                   predict_displacement=False, **PLAIN_LSTM),
    # a GRU reading every input feature (their state rides in the carry)
    DynamicsConfig(hidden=8, layers=1, cell="gru", condition_on_initial_pose=True,
                   pressure_delta=True, step_size=True, step_decays=(1.0, 5.0),
                   play_widths_kpa=(0.3, 1.0), step_threshold_kpa=0.5,
                   pressure_transients=(1.0, 4.0)),
]


@pytest.mark.parametrize("config", CONFIGS)
def test_stepped_equals_sequence(config):
    params = make_params(config)
    run = make_runs(1, 25, seed=5)[0]
    pressures, initial_pose = jnp.asarray(run.pressures_kpa), jnp.asarray(run.positions_m[0])
    whole = predict_sequence(params, pressures, initial_pose)
    assert whole.shape == (25, 3)

    step = jax.jit(dynamics.step)
    carry = dynamics.init_carry(params, initial_pose)
    stepped = []
    for t in range(25):
        carry, position = step(params, carry, pressures[t])
        stepped.append(position)
    np.testing.assert_allclose(np.stack(stepped), whole, rtol=1e-5, atol=1e-7)


def test_step_held_is_repeated_steps():
    params = make_params(CONFIGS[0])
    carry = dynamics.init_carry(params, jnp.array([0.03, 0.35, 0.2]))
    pressure = jnp.array([2.0, 3.0, 1.0])
    held_carry, held = dynamics.step_held(params, carry, pressure, 5)
    whole = predict_sequence(params, jnp.tile(pressure, (5, 1)), carry.initial_pose)
    assert held.shape == (5, 3)
    np.testing.assert_allclose(held, whole, rtol=1e-5, atol=1e-7)
    assert jax.tree.structure(held_carry) == jax.tree.structure(carry)


def test_initial_pose_conditioning_and_displacement():
    conditioned = make_params(CONFIGS[0])
    pressures = jnp.full((6, 3), 2.0)
    pose_a, pose_b = jnp.array([0.03, 0.35, 0.2]), jnp.array([0.033, 0.352, 0.203])
    out_a = predict_sequence(conditioned, pressures, pose_a)
    out_b = predict_sequence(conditioned, pressures, pose_b)
    # Displacement target: the offset of the initial pose passes through, plus the carry effect.
    assert not np.allclose(out_b - out_a, 0.0)

    plain = make_params(DynamicsConfig(hidden=8, condition_on_initial_pose=False,
                                       predict_displacement=True))
    shift = predict_sequence(plain, pressures, pose_b) - predict_sequence(
        plain, pressures, pose_a
    )
    np.testing.assert_allclose(shift, np.broadcast_to(pose_b - pose_a, (6, 3)), atol=1e-6)

    absolute = make_params(CONFIGS[1])
    np.testing.assert_allclose(
        predict_sequence(absolute, pressures, pose_a),
        predict_sequence(absolute, pressures, pose_b),
        atol=1e-7,
    )


def test_normalizer_statistics():
    runs = make_runs()
    normalizer = dynamics.fit_normalizer(runs, predict_displacement=True)
    all_p = np.concatenate([r.pressures_kpa for r in runs])
    np.testing.assert_allclose(normalizer.pressure_mean, all_p.mean(0), rtol=1e-5)
    np.testing.assert_allclose(normalizer.pressure_std, all_p.std(0), rtol=1e-4)
    displacement = np.concatenate([r.positions_m - r.positions_m[0] for r in runs])
    np.testing.assert_allclose(normalizer.target_mean, displacement.mean(0), atol=1e-6)


def test_shape_asserts():
    params = make_params(CONFIGS[0])
    with pytest.raises(AssertionError):
        predict_sequence(params, jnp.zeros((5, 2)), jnp.zeros(3))
    with pytest.raises(AssertionError):
        dynamics.init_carry(params, jnp.zeros(2))


# ---------------------------------------------------------------------------------------------
# recurrent dropout
# ---------------------------------------------------------------------------------------------
def flax_gru_and_inputs(seed):
    """flax's GRUCell with 8 units, its variables, an input ``x`` [5] and a state ``h`` [8]."""
    import flax.linen as nn

    x, h = jnp.linspace(-1.0, 1.0, 5), jnp.linspace(0.5, -0.5, 8)
    cell = nn.GRUCell(8)
    return cell, cell.init(jax.random.PRNGKey(seed), h, x), x, h


def test_dropout_gru_cell_is_flax_gru_cell_without_a_mask():
    flax_cell, variables, x, h = flax_gru_and_inputs(1)
    ours = dynamics.DropoutGRUCell(8)
    assert (jax.tree.structure(ours.init(jax.random.PRNGKey(1), h, x))
            == jax.tree.structure(variables))
    expected, _ = flax_cell.apply(variables, h, x)
    unmasked, _ = ours.apply(variables, h, x)
    all_kept, _ = ours.apply(variables, h, x, jnp.ones(8))
    np.testing.assert_allclose(unmasked, expected, rtol=1e-6)
    np.testing.assert_allclose(all_kept, expected, rtol=1e-6)


def test_dropout_gru_cell_masks_only_the_recurrent_products():
    """With every unit dropped, the gates and the candidate see h = 0, while the update still
    carries the unmasked h: h' = GRU(0, x) + z(x) h, where z(x) = sigmoid(W_iz x + b_iz)."""
    flax_cell, variables, x, h = flax_gru_and_inputs(2)
    from_zero, _ = flax_cell.apply(variables, jnp.zeros(8), x)
    iz = variables["params"]["iz"]
    z = jax.nn.sigmoid(x @ iz["kernel"] + iz["bias"])
    dropped, _ = dynamics.DropoutGRUCell(8).apply(variables, h, x, jnp.zeros(8))
    np.testing.assert_allclose(dropped, from_zero + z * h, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("cell", ["gru", "lstm"])
def test_recurrent_dropout_keeps_the_state_bounded_over_a_long_rollout(cell):
    """An LSTM's and a GRU's h stay in [-1, 1]: dropout rescales what enters the recurrent
    products, never the state itself (rescaling a GRU's carry by 1 / (1 - rate) every step
    made it grow without bound)."""
    config = DynamicsConfig(hidden=16, layers=2, cell=cell)
    params = make_params(config)
    network = dynamics.make_network(config)
    rate = 0.5
    mask = jax.random.bernoulli(jax.random.PRNGKey(3), 1 - rate, (2, 16)) / (1 - rate)
    inputs = jax.random.normal(jax.random.PRNGKey(4), (2000, config.input_dim)) * 3.0

    def one_step(carry, x):
        carry, _ = network.apply(params.network, carry, x, mask)
        return carry, carry

    carry0 = network.apply(params.network, jnp.zeros(3), method=type(network).initial_carry)
    _, states = jax.lax.scan(one_step, carry0, inputs)
    hs = [layer if cell == "gru" else layer[1] for layer in states]
    assert all(bool(jnp.all(jnp.isfinite(h))) and float(jnp.abs(h).max()) <= 1.0 for h in hs)


@pytest.mark.parametrize("cell", ["gru", "lstm"])
def test_recurrent_dropout_rollout_with_all_units_kept_is_the_plain_rollout(cell):
    params = make_params(DynamicsConfig(hidden=8, layers=2, cell=cell))
    inputs = jax.random.normal(jax.random.PRNGKey(5), (30, params.config.input_dim))
    pose = dynamics.normalize_pose(params.normalizer, jnp.array([0.03, 0.35, 0.2]))
    rollout = jax.jit(dynamics.predict_normalized)  # one program for both masks
    plain = rollout(params, inputs, pose)
    kept = rollout(params, inputs, pose, jnp.ones((2, 8)))
    dropped = rollout(params, inputs, pose, jnp.zeros((2, 8)))
    np.testing.assert_allclose(kept, plain, rtol=1e-5, atol=1e-6)
    assert float(jnp.abs(dropped - plain).max()) > 1e-3


def test_the_saved_architecture_is_the_model_schema():
    """One declaration: the model config's architecture fields, their defaults included, are
    the saved model's config (``DynamicsConfig``), lists frozen to tuples."""
    import dataclasses

    from pipeline.dynamics.training import ModelTrainConfig
    from pipeline.schemas import ModelArchitecture, ModelConfig

    names = [f.name for f in dataclasses.fields(ModelArchitecture)]
    assert [f.name for f in dataclasses.fields(DynamicsConfig)] == names
    assert set(names) < {f.name for f in dataclasses.fields(ModelConfig)}
    settings = ModelTrainConfig.from_any(ModelConfig(hidden=12, step_decays=[2.0]))
    assert settings.architecture() == DynamicsConfig(hidden=12, step_decays=(2.0,))
    assert DynamicsConfig().cell == "gru" and DynamicsConfig().step_decays == ()
    assert DynamicsConfig().pressure_transients == (1.0, 3.0, 10.0)
    with pytest.raises(ValueError, match="cell must be one of"):
        DynamicsConfig(cell="rnn")
