"""Training results: the return curve leaves out the warm-up updates."""

from __future__ import annotations

import numpy as np

from pipeline.rl.results import metrics_table, return_curves, warmup_updates


def test_warmup_lasts_until_an_episode_can_have_run_its_full_length():
    # 40-period episodes, 32-step rollouts: update 0 (steps 0..31) only sees early endings
    assert warmup_updates(40, 32) == 1
    assert warmup_updates(32, 32) == 0  # an episode can end by truncation in update 0
    assert warmup_updates(100, 32) == 3  # steps 0..127 first reach 100 in update 3
    assert warmup_updates(1, 32) == 0


def test_return_curves_leave_out_the_warmup_spike():
    # update 0: only the lucky early finishers (-50); later the policy's real level (-300), with
    # an update where no episode ended (NaN): the seed's previous value is carried
    returns = np.array([[-50.0, -300.0, np.nan, -280.0], [-55.0, -310.0, -290.0, -270.0]])
    metrics = metrics_table({"timesteps": np.tile(np.arange(1, 5) * 2048, (2, 1)),
                             "mean_return": returns}, max_episode_steps=40, rollout_steps=32)
    assert metrics["warmup"].tolist() == [True, False, False, False] * 2
    curves = return_curves(metrics)
    assert curves["timesteps"].min() == 4096
    seed0 = curves[curves["seed"] == 0]["return"].tolist()
    assert seed0 == [-300.0, -300.0, -280.0]
