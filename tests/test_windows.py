import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pipeline.data.windows import (
    batches_per_epoch,
    gather_windows,
    make_windows,
    sample_batch,
    split_runs,
)


def test_split_runs_is_deterministic_and_order_independent():
    ids = [f"run_{i}" for i in range(8)]
    train, test = split_runs(ids, 0.75, seed=3)
    assert (train, test) == split_runs(list(reversed(ids)), 0.75, seed=3)
    assert len(train) == 6 and len(test) == 2
    assert sorted(train + test) == ids
    assert train == sorted(train) and test == sorted(test)


def test_split_runs_seed_changes_split_and_keeps_both_sides():
    ids = [f"run_{i}" for i in range(8)]
    splits = {tuple(split_runs(ids, 0.75, seed)[1]) for seed in range(10)}
    assert len(splits) > 1
    assert split_runs(["a", "b"], 0.99, 0) in ((["a"], ["b"]), (["b"], ["a"]))
    assert split_runs(["a", "b"], 1.0, 0) == (["a", "b"], [])
    with pytest.raises(ValueError):
        split_runs(["a", "a"], 0.5, 0)


def test_make_windows_known_answer():
    windows = make_windows([5, 2, 4], length=3, stride=2)
    # run 0 (rows 0..4): starts 0, 2; run 1 too short; run 2 (rows 7..10): start 7 only.
    np.testing.assert_array_equal(windows.starts, [0, 2, 7])
    np.testing.assert_array_equal(windows.run_index, [0, 0, 2])
    np.testing.assert_array_equal(windows.offset_in_run, [0, 2, 0])
    assert windows.length == 3
    assert len(make_windows([5], length=1, stride=1).starts) == 5
    assert len(make_windows([2], length=3, stride=1).starts) == 0


def test_gather_windows_known_answer():
    series = jnp.arange(20.0).reshape(10, 2)
    batch = gather_windows(series, jnp.array([0, 7]), 3)
    assert batch.shape == (2, 3, 2)
    np.testing.assert_array_equal(batch[1, :, 0], [14.0, 16.0, 18.0])


def test_sequential_order_walks_windows_in_time_order():
    indices = [np.asarray(sample_batch(jax.random.PRNGKey(0), s, 7, 3, "sequential"))
               for s in range(3)]
    # 7 windows, batches of 3: two batches per epoch, then the walk restarts.
    assert batches_per_epoch(7, 3) == 2
    np.testing.assert_array_equal(indices, [[0, 1, 2], [3, 4, 5], [0, 1, 2]])


def test_permuted_order_covers_each_epoch_once_and_reshuffles():
    key = jax.random.PRNGKey(1)
    epoch0 = np.concatenate([sample_batch(key, s, 12, 4, "permuted") for s in range(3)])
    epoch1 = np.concatenate([sample_batch(key, s, 12, 4, "permuted") for s in range(3, 6)])
    np.testing.assert_array_equal(np.sort(epoch0), np.arange(12))
    np.testing.assert_array_equal(np.sort(epoch1), np.arange(12))
    assert not np.array_equal(epoch0, epoch1)
    np.testing.assert_array_equal(sample_batch(key, 4, 12, 4, "permuted"), epoch1[4:8])


def test_sample_batch_wraps_when_fewer_windows_than_batch():
    indices = np.asarray(sample_batch(jax.random.PRNGKey(0), 0, 2, 5, "sequential"))
    np.testing.assert_array_equal(indices, [0, 1, 0, 1, 0])
    with pytest.raises(ValueError):
        sample_batch(jax.random.PRNGKey(0), 0, 2, 5, "shuffled")


def test_padded_window_list_draws_the_batches_of_the_unpadded_one():
    key = jax.random.PRNGKey(2)
    for step in range(7):  # three epochs of 10 windows in batches of 4 (2 per epoch)
        unpadded = sample_batch(key, step, 10, 4, "permuted")
        padded = sample_batch(key, step, jnp.asarray(10), 4, "permuted", capacity=23)
        np.testing.assert_array_equal(padded, unpadded)
        assert np.asarray(padded).max() < 10  # never a padding slot
