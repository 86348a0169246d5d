"""The exploration walk (paper eq. 1): safety for every alpha, beta and seed, and the formula."""

from __future__ import annotations

from types import SimpleNamespace

import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.arm.exploration import exploration_run, plot_walks, random_walk
from pipeline.arm.safety import SafeSet

LIMITS = SimpleNamespace(p_min=0.0, p_max=7.0, sum_max=13.0, preload=2.0)


def walk_config(**changes):
    base = dict(seed=0, alpha=0.5, beta=0.15, p_max=13.0, noise_std=1.5, num_steps=64,
                pad_steps=3, figure_alphas=[0.0, 0.9])
    return SimpleNamespace(**{**base, **changes})


@settings(max_examples=200, deadline=None)
@given(
    alpha=st.floats(0.0, 1.0),
    beta=st.floats(-3.0, 3.0),
    p_max=st.floats(6.0, 30.0),
    noise_std=st.floats(0.0, 5.0),
    seed=st.integers(0, 2**31 - 1),
    p_min=st.sampled_from([-3.0, 0.0, 0.5]),
)
def test_every_step_is_safe_for_any_alpha_beta_seed(alpha, beta, p_max, noise_std, seed, p_min):
    limits = SimpleNamespace(p_min=p_min, p_max=7.0, sum_max=13.0, preload=2.0)
    cfg = walk_config(alpha=alpha, beta=beta, p_max=p_max, noise_std=noise_std)
    p = exploration_run(jax.random.key(seed), cfg, limits)
    assert p.shape == (3 + 64 + 3, 3)
    assert np.all(np.isfinite(p))
    assert np.all(p >= limits.p_min) and np.all(p <= limits.p_max)
    assert np.all(p.sum(axis=1) <= min(p_max, limits.sum_max))


def test_a_ceiling_below_the_preload_is_rejected():
    with pytest.raises(ValueError, match=r"exploration\.p_max"):
        exploration_run(jax.random.key(0), walk_config(p_max=5.0), LIMITS)


def test_runs_start_and_end_at_the_preload():
    p = exploration_run(jax.random.key(3), walk_config(), LIMITS)
    np.testing.assert_array_equal(p[:3], 2.0)
    np.testing.assert_array_equal(p[-3:], 2.0)
    assert np.abs(p[3:-3] - 2.0).max() > 0.5  # and explores in between


def test_walk_matches_equation_one_step_by_step():
    """Re-derive each step with numpy from the same normal draws (sum within the limits)."""
    key, alpha, beta, p_max, preload, std = jax.random.key(7), 0.6, 0.2, 13.0, 2.0, 0.5
    safe = SafeSet.from_limits(SimpleNamespace(p_min=-10.0, p_max=10.0, sum_max=13.0))
    walk = np.asarray(random_walk(key, alpha, beta, p_max, preload, std, safe, 20), np.float64)
    draws = [preload + std * np.asarray(jax.random.normal(k, (3,)), np.float64)
             for k in jax.random.split(key, 20)]
    p = np.full(3, preload)
    for i in range(20):
        p_star = alpha * p + (1 - alpha) * draws[i]
        total = p_star.sum()
        expected = p_max / (1 + np.exp(-beta * total)) * p_star / total
        np.testing.assert_allclose(walk[i], expected, rtol=1e-4, atol=1e-4)
        # the rescaled pressures sum to P_max * sigmoid(beta * S) < P_max
        assert walk[i].sum() < p_max
        p = walk[i]


def test_alpha_one_holds_the_pressure_differences():
    """With alpha = 1 no noise enters; the shares of the preload stay equal."""
    p = exploration_run(jax.random.key(0), walk_config(alpha=1.0), LIMITS)
    np.testing.assert_allclose(p[:, 0], p[:, 1], atol=1e-5)
    np.testing.assert_allclose(p[:, 1], p[:, 2], atol=1e-5)


def test_same_seed_same_walk_other_seed_other_walk():
    a = exploration_run(jax.random.key(1), walk_config(), LIMITS)
    b = exploration_run(jax.random.key(1), walk_config(), LIMITS)
    c = exploration_run(jax.random.key(2), walk_config(), LIMITS)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)


def test_figure_of_several_alphas_is_written(tmp_path):
    path = plot_walks(tmp_path / "walks.png", jax.random.key(0), walk_config(), LIMITS, 2.0)
    assert path.stat().st_size > 10_000
