import jax
import numpy as np
import pytest

from pipeline.data.runs import Run
from pipeline.dynamics import checkpoints, scoring
from pipeline.dynamics import training as train_model
from pipeline.dynamics.training import ModelTrainConfig


def first_order_runs(num_runs=3, num_steps=60, seed=0):
    """Position follows a first-order lag of a linear map of held pressures (learnable)."""
    rng = np.random.default_rng(seed)
    gain = np.array([[2.0, -1.0, 0.0], [0.5, 0.5, 0.5], [0.0, 1.0, -2.0]]) * 1e-3
    runs = []
    for i in range(num_runs):
        commands = rng.uniform(0.0, 5.0, (num_steps // 5 + 1, 3))
        pressure = np.repeat(commands, 5, axis=0)[:num_steps]
        rest = np.array([0.03, 0.35, 0.2]) + rng.normal(0, 0.002, 3)
        position, state = [], np.zeros(3)
        for p in pressure:
            state = 0.6 * state + 0.4 * gain @ p
            position.append(rest + state)
        runs.append(Run(f"run{i}", np.arange(num_steps) / 10.0, pressure.astype(np.float32),
                        np.array(position, np.float32)))
    return runs


TINY = {
    "hidden": 16, "layers": 1, "head": [], "condition_on_initial_pose": True,
    "predict_displacement": True, "batch_size": 8, "learning_rate": 1e-2,
    "lr_schedule": "constant", "num_steps": 60, "eval_every": 20, "checkpoint_every": 20,
}


def test_tiny_training_loss_falls():
    runs = first_order_runs()
    params, normalizer, table = train_model.fit(
        runs[:2], TINY, window=16, val_runs=runs[2:], progress=False
    )
    assert list(table.columns) == train_model.LOSS_TABLE_COLUMNS
    assert len(table) == 60
    assert table.train_loss.iloc[-10:].mean() < 0.5 * table.train_loss.iloc[:5].mean()
    val = table.dropna()
    assert list(val.step) == [20, 40, 60]
    assert val.val_mean_mm.iloc[-1] < val.val_mean_mm.iloc[0]
    assert params.normalizer is normalizer
    assert scoring.evaluate_open_loop(params, runs[2])["mean_mm"] == pytest.approx(
        val.val_mean_mm.iloc[-1], rel=1e-4
    )


def test_resume_equals_uninterrupted(tmp_path):
    runs = first_order_runs(2, 40)
    config = dict(TINY, num_steps=40, lr_schedule="cosine", warmup_steps=5)
    full, _, full_table = train_model.fit(runs, config, window=12, progress=False)

    folder = tmp_path / "ckpt"
    train_model.fit(runs, config, window=12, checkpoint_dir=folder, progress=False,
                    stop_after_steps=20)
    assert checkpoints.latest_checkpoint(folder).name == "step_00000020.msgpack"
    resumed, _, resumed_table = train_model.fit(
        runs, config, window=12, checkpoint_dir=folder, progress=False
    )
    assert checkpoints.latest_checkpoint(folder).name == "step_00000040.msgpack"
    for a, b in zip(jax.tree.leaves(full.network), jax.tree.leaves(resumed.network)):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(full_table.train_loss, resumed_table.train_loss)

    with pytest.raises(ValueError, match="different training setup"):
        train_model.fit(runs, dict(config, learning_rate=0.5), window=12,
                        checkpoint_dir=folder, progress=False)


def test_time_budget_stops_after_the_chunk_that_spends_it(tmp_path):
    runs = first_order_runs(2, 40)
    folder = tmp_path / "ckpt"
    _, _, table = train_model.fit(runs, TINY, window=12, progress=False, time_budget_s=0.0,
                                  checkpoint_dir=folder)
    assert len(table) == 20  # one chunk of gcd(eval_every, checkpoint_every) steps, then stop
    assert checkpoints.latest_checkpoint(folder).name == "step_00000020.msgpack"


def test_checkpoint_round_trip(tmp_path):
    runs = first_order_runs(2, 30)
    params, _, _ = train_model.fit(runs, dict(TINY, num_steps=5), window=10, progress=False,
                                   checkpoint_dir=tmp_path)
    for path in (tmp_path / "model.msgpack", checkpoints.latest_checkpoint(tmp_path)):
        if path.name == "model.msgpack":
            checkpoints.save_dynamics(path, params)
        loaded = checkpoints.load_dynamics(path)
        assert loaded.config == params.config
        run = runs[0]
        np.testing.assert_array_equal(
            scoring.predict_run(loaded, run), scoring.predict_run(params, run)
        )
    assert not list(tmp_path.glob("*.tmp"))


def test_config_from_any_rejects_unknown_keys():
    assert ModelTrainConfig.from_any({"hidden": 7, "head": [3]}).head == (3,)
    with pytest.raises(ValueError, match="unknown model config keys"):
        ModelTrainConfig.from_any({"hiden": 7})
    paper = ModelTrainConfig.from_any(
        {"hidden": 1024, "batch_size": 64, "learning_rate": 1e-3, "lr_schedule": "constant",
         "num_steps": 200_000, "condition_on_initial_pose": False,
         "predict_displacement": False}
    )
    assert paper.architecture().hidden == 1024


def test_position_errors_known_answer():
    observed = np.zeros((4, 3))
    predicted = np.array([[0.003, 0.004, 0.0]] * 3 + [[0.0, 0.0, 0.001]])  # 5, 5, 5, 1 mm
    errors = scoring.position_errors_mm(predicted, observed)
    assert errors["mean_mm"] == pytest.approx(4.0)
    assert errors["p95_mm"] == pytest.approx(5.0)


def test_baseline_mean_position_known_answer():
    times, pressures = np.arange(2) / 10.0, np.zeros((2, 3))
    train = [Run("a", times, pressures, np.array([[0.0, 0.0, 0.0], [0.002, 0.0, 0.0]]))]
    test = Run("b", times, pressures, np.array([[0.001, 0.0, 0.0], [0.001, 0.003, 0.0]]))
    errors = scoring.baseline_mean_position(train, test)
    assert errors["mean_mm"] == pytest.approx(1.5)


def test_lagged_features_and_linear_baseline_known_answer():
    pressure = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]])
    features = scoring.lagged_features(pressure, num_lags=2)
    assert features.shape == (3, 13)
    # Row 0: bias, p_0, p_{-1} (= p_0, the preload), then squares.
    np.testing.assert_array_equal(features[0], [1, 1, 2, 3, 1, 2, 3, 1, 4, 9, 1, 4, 9])
    np.testing.assert_array_equal(features[2, 1:7], [7, 8, 9, 4, 5, 6])

    # A position that is exactly linear in p_t, p_{t-1} and p_t**2 is recovered exactly.
    rng = np.random.default_rng(0)
    p = rng.uniform(0, 5, (200, 3))
    previous = np.concatenate([p[:1], p[:-1]])
    pos = 0.01 + 1e-3 * (p[:, [0, 1, 2]] - 0.5 * previous + 0.1 * p**2)
    run = Run("r", np.arange(200) / 10.0, p, pos)
    errors = scoring.baseline_linear_lagged([run], run, num_lags=2)
    assert errors["mean_mm"] < 1e-6


def test_a_corrupt_checkpoint_is_named_and_set_aside(tmp_path, caplog):
    """The newest checkpoint was cut off; the one before it is resumed from."""
    runs = first_order_runs(2, 40)
    config = dict(TINY, num_steps=40)
    folder = tmp_path / "ckpt"
    train_model.fit(runs, config, window=12, checkpoint_dir=folder, progress=False,
                    stop_after_steps=20)
    corrupt = folder / "step_00000030.msgpack"
    corrupt.write_bytes(b"\x85\xa5model\x00cut off")
    with caplog.at_level("WARNING"):
        _, _, table = train_model.fit(runs, config, window=12, checkpoint_dir=folder,
                                      progress=False)
    assert f"checkpoint {corrupt} cannot be read" in caplog.text
    assert f"moved it to {corrupt}.corrupt and trying the one before" in caplog.text
    assert (folder / "step_00000030.msgpack.corrupt").is_file() and not corrupt.exists()
    assert list(table.step) == list(range(1, 41))  # 20 restored + 20 trained


def test_window_losses_known_answer(monkeypatch):
    """Two steps of error, standardized (3, 0, 0) and (0, 1, 1), target std (1, 2, 2) mm: the
    squared error averages 11 / 6; the distances are 3 and 2 sqrt(2) mm, in units of the mean
    std (5 / 3 mm) 1.8 and 1.697."""
    import jax.numpy as jnp

    from pipeline.dynamics import model as dynamics

    outputs = jnp.asarray([[[3.0, 0.0, 0.0], [0.0, 1.0, 1.0]]])  # [B=1, W=2, 3]
    monkeypatch.setattr(dynamics, "predict_normalized",
                        lambda params, inputs, pose, mask: outputs[0])
    ones, zeros = jnp.ones(3), jnp.zeros(3)
    normalizer = dynamics.Normalizer(pressure_mean=zeros, pressure_std=ones, pose_mean=zeros,
                                     pose_std=ones, target_mean=zeros,
                                     target_std=jnp.asarray([1e-3, 2e-3, 2e-3]))
    params = dynamics.DynamicsParams(network={}, normalizer=normalizer,
                                     config=dynamics.DynamicsConfig(predict_displacement=False))
    args = (params, jnp.zeros((1, 2, 4)), jnp.zeros((1, 2, 3)), jnp.zeros((1, 3)))
    assert float(train_model.window_loss(*args)) == pytest.approx(11 / 6, rel=1e-6)
    assert float(train_model.window_loss(*args, loss="distance")) == pytest.approx(
        (1.8 + 1.2 * np.sqrt(2)) / 2, rel=1e-5)
    with pytest.raises(ValueError, match="mse or distance"):
        train_model.window_loss(*args, loss="l1")


def test_a_distance_trained_model_learns_too():
    runs = first_order_runs()
    settings = {**TINY, "loss": "distance", "learning_rate": 3e-3, "num_steps": 120}
    _, _, table = train_model.fit(runs[:2], settings, window=16, val_runs=runs[2:],
                                  progress=False)
    assert table.train_loss.iloc[-10:].mean() < 0.6 * table.train_loss.iloc[:5].mean()
    val = table.dropna()
    assert val.val_mean_mm.iloc[-1] < val.val_mean_mm.iloc[0]
    with pytest.raises(ValueError, match="loss must be mse or distance"):
        ModelTrainConfig.from_any({"loss": "huber"})
