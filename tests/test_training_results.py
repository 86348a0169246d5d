"""Training results: the return curve leaves out the warm-up updates; the progress bar never
counts past its total, even when the seeds' callbacks arrive at once."""

from __future__ import annotations

import threading

import numpy as np

from pipeline.rl.ppo import ThrottledProgress
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


def test_progress_never_overruns_its_total_under_concurrent_callbacks():
    bar = ThrottledProgress(total=50, min_interval_s=0.0)  # drawn on the captured stderr
    start = threading.Barrier(4)

    def seed_callbacks():
        start.wait()
        for update in range(60):  # more calls than updates, as a runaway index would give
            bar(np.asarray(update), np.asarray(-1.0))

    threads = [threading.Thread(target=seed_callbacks) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert bar.bar.n == 50 and bar.done == 50
    bar.close()
