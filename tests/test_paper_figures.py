"""`make figures` stays working: the figures command, shrunk (few steps, seeds and recordings)."""

from __future__ import annotations

import pytest

# every stage the figures run, made small: seconds of fitting and training, not minutes
SHRUNK = ["exploration.num_steps=24", "exploration.pad_steps=2",
          "exploration.figure_alphas=[0.0,0.8]",
          "model.hidden=8", "model.num_steps=6", "model.eval_every=3", "model.checkpoint_every=3",
          "dataset.window=16", "agent.num_envs=16", "agent.num_steps=16", "env.max_steps=10", "agent.num_evals=1",
          "agent.eval_envs=4", "env.reset_bank_size=4", "agent.progress=false"]
# the three shortest recordings (a split needs a held-out run, the cv protocol two folds)
RECORDINGS = ["Step_control_17_10_12_20.csv", "Step_control_17_10_12_29.csv",
              "Step_control_17_10_12_03.csv"]


@pytest.mark.slow  # among the longest of the suite: runs with `make test-all`
def test_the_figures_command_writes_figs_4_to_8(sorolex_dir, tmp_path):
    from experiments.paper_figures import main

    data = tmp_path / "data"
    data.mkdir()
    for name in RECORDINGS:
        if not (sorolex_dir / name).is_file():
            pytest.skip(f"{name} not in {sorolex_dir}")
        (data / name).symlink_to(sorolex_dir / name)  # read in place, never copied
    out = tmp_path / "figures"
    main(["--out", str(out), "--output-dir", str(tmp_path / "outputs"), "--seeds", "2",
          "--ppo-steps", "1024", "--set", f"paths.data_dir={data}", *SHRUNK])
    names = {"fig4_exploration_walk.png", "fig5_task_space_alphas.png",
             "fig6_loss_permuted_vs_sequential.png", "fig7_reconstruction.png",
             "fig8_returns_ff_vs_rnn.png"}
    assert names <= {p.name for p in out.iterdir()}
    captions = (out / "captions.md").read_text()
    for name in names:
        assert f"![{name}]({name})" in captions
    # Fig. 6 compares validation losses: one split of the three runs, two training runs
    assert "(2 training runs, validation on 1 held-out" in captions
    assert "dataset.protocol=split" in captions
    # the caption compares with the project's configuration, not with the shrunk one
    assert "a GRU of 8 units instead of the paper's LSTM of 1024" in captions
    assert "1,024 steps per seed instead of 2,000,000" in captions
