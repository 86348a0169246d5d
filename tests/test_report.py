"""The report writer lays out text, tables and figures in Markdown and a self-contained HTML page;
the report's sections label their columns and never hide who did not get there."""

from __future__ import annotations

import base64
import re

import numpy as np
import pandas as pd

from pipeline.evaluation.figures import after_arrival_figure, tail_episodes
from pipeline.evaluation.metrics import median_steps, seed_spread, summarize
from pipeline.evaluation.report import Figure, Section, Table, format_number, write_report
from pipeline.evaluation.sections import consecutive_table

PNG = b"\x89PNG\r\n\x1a\n-not-a-real-image"


def test_report_has_every_section_table_and_figure(tmp_path):
    figure = tmp_path / "artifacts" / "key" / "figures" / "fig.png"
    figure.parent.mkdir(parents=True)
    figure.write_bytes(PNG)
    sections = [
        Section("Configuration", ["Robot `sim`, **4** runs.", "```yaml\na: 1\n```"]),
        Section("Results", [Table(pd.DataFrame({"policy": ["ff", "a|b"], "mm": [0.51234, None]}),
                                  "final distance"), Figure(figure, "a figure")]),
    ]
    md, page = write_report(tmp_path / "report", "Run", sections)
    text = md.read_text()
    assert "## Configuration" in text and "## Results" in text
    assert "| policy | mm |" in text and "| ff | 0.512 |" in text and "a\\|b" in text
    # the Markdown links a copy of the figure beside it
    link = re.search(r"!\[a figure\]\((.+?)\)", text).group(1)
    assert not link.startswith("..") and (md.parent / link).read_bytes() == PNG
    markup = page.read_text()
    assert "<code>sim</code>" in markup and "<b>4</b>" in markup
    assert "<pre>" in markup and markup.count("<h2") == 2 and "<details>" in markup


def test_the_html_report_is_self_contained(tmp_path):
    figure = tmp_path / "elsewhere" / "fig.png"
    figure.parent.mkdir()
    figure.write_bytes(PNG)
    _, page = write_report(tmp_path / "report", "Run", [Section("S", [Figure(figure, "f")])])
    moved = tmp_path / "copied.html"
    page.rename(moved)
    figure.unlink()  # the page needs neither its folder nor the figure's
    sources = re.findall(r"src='([^']*)'", moved.read_text())
    assert len(sources) == 1 and sources[0].startswith("data:image/png;base64,")
    assert base64.b64decode(sources[0].split(",", 1)[1]) == PNG
    assert "href=" not in moved.read_text().replace('href="#s0"', "")


def test_numbers_keep_three_significant_figures():
    assert [format_number(v) for v in (0.47, 0.567, 12.0, 0.0625, 1234.5, 0.0)] == \
        ["0.470", "0.567", "12.0", "0.0625", "1,234", "0"]
    assert format_number(float("inf")) == "∞" and format_number(float("nan")) == "–"
    page = Table(pd.DataFrame({"a": [0.47, 0.567]}))
    text = write_report_text(page)
    assert "0.470" in text and "0.567" in text


def write_report_text(table: Table) -> str:
    from pipeline.evaluation.report import render_html

    return render_html("t", [Section("s", [table])])


def test_steps_to_3mm_count_the_episodes_that_never_got_there():
    # 7 episodes: 1 starts within 3 mm (step 0), 6 never get there; a median over the one that
    # did would say 0 steps
    table = pd.DataFrame({"controller": "preload", "final_distance_mm": np.arange(7.0) + 4,
                          "success_1mm": False, "success_3mm": False,
                          "steps_to_3mm": [0.0] + [np.nan] * 6, "smoothness_kpa": 0.0,
                          "time_above_limits": 0.0})
    row = summarize(table, ["controller"]).iloc[0]
    assert row["reached_3mm"] == 1 / 7
    assert row["median_steps_to_3mm"] == np.inf
    # 3 of 4 got there at 2, 4, 6 steps: the median over all four is between 4 and 6
    assert median_steps(pd.Series([2.0, 4.0, 6.0, np.nan])) == 5.0


def test_seed_spread_is_over_each_seeds_median():
    episodes = pd.DataFrame({"controller": "ff", "plant": "learned",
                             "seed": [0, 0, 0, 1, 1, 1, 2, 2, 2],
                             "final_distance_mm": [1, 2, 9, 3, 4, 5, 0.5, 0.6, 0.7]})
    row = seed_spread(episodes, ["controller", "plant"]).iloc[0]
    # seed medians 2, 4, 0.6
    assert row["seeds"] == 3 and row["median_of_seed_medians"] == 2.0
    assert row["min"] == 0.6 and row["max"] == 4.0 and row["q25"] == 1.3 and row["q75"] == 3.0


def test_consecutive_goals_table_has_one_labelled_column_per_goal(tmp_path):
    rows = [{"plant": plant, "controller": "ppo_ff", "seed": seed, "goal": goal,
             "median_distance_mm": 1.0 + goal + seed, "success_3mm": 1.0 if goal == 0 else 0.0}
            for plant in ("learned", "plant") for seed in (0, 1) for goal in range(3)]
    table = consecutive_table(pd.DataFrame(rows))
    assert list(table.columns) == ["controller", "evaluated on", "goal 1 [mm]", "goal 2 [mm]",
                                   "goal 3 [mm]", "fraction ≤ 3 mm"]
    assert table["evaluated on"].tolist() == ["learned model", "simulated arm"]
    # median over the seeds (1 and 2 at goal 1), a third of the goals within 3 mm
    assert table["goal 1 [mm]"].tolist() == [1.5, 1.5] and table["fraction ≤ 3 mm"].tolist() == [1 / 3] * 2
    _, page = write_report(tmp_path, "Run", [Section("C", [Table(table)])])
    headers = re.findall(r"<th>(.*?)</th>", page.read_text())
    assert all(h.strip() for h in headers) and len(headers) == 6


def test_the_evaluation_report_has_one_summary_and_opens_with_it(tmp_path):
    """The table the run printed at its end, the model's accuracy, what the plants are and each
    controller's median per plant: all under one "Summary" heading, the report's first."""
    from pipeline.evaluation.sections import ReportFacts, report_sections
    from pipeline.infra.records import ArtifactRecord

    controllers, plants = ["ppo_ff", "preload"] * 2, ["learned"] * 2 + ["plant"] * 2
    summary = pd.DataFrame({"controller": controllers, "plant": plants, "episodes": 4,
                            "median_final_mm": [0.6, 9.3, 0.8, 9.1],
                            "success_1mm": [0.75, 0.0, 0.5, 0.0],
                            "smoothness_kpa": [0.1, 0.0, 0.1, 0.0]})
    episodes = pd.DataFrame({"controller": np.repeat(controllers, 2),
                             "plant": np.repeat(plants, 2), "seed": [0, 1] * 4,
                             "final_distance_mm": [0.5, 0.7, 9.3, 9.3, 0.7, 0.9, 9.1, 9.1]})
    metrics = pd.DataFrame([{"split": split, "run_id": run, "model": name, "mean_mm": 1.0,
                             "p95_mm": 2.0}
                            for split, run in (("train", "r1"), ("test", "r2"))
                            for name in ("learned", "linear_lagged", "mean_position")])
    model = ArtifactRecord("fit_model", "m", tmp_path / "model", tables={"metrics": metrics},
                           summary={"learned_mean_mm": 1.0, "learned_p95_mm": 2.0,
                                    "mean_position_mean_mm": 9.0, "linear_lagged_mean_mm": 4.0,
                                    "train_runs": ["r1"], "test_runs": ["r2"]})
    image = tmp_path / "artifacts" / "key" / "figures" / "fig.png"
    image.parent.mkdir(parents=True)
    image.write_bytes(PNG)
    figures = {name: Figure(image, name) for name in ("returns", "distance", "trajectories")}
    facts = ReportFacts("sim", 0.5, 0.5, 30.0, 32, 10.0, ("ppo_ff",), ("preload",), 20, 3,
                        "a: 1\n")
    results = {"tables": {"summary": summary, "episodes": episodes,
                          "plant_gap": pd.DataFrame(), "consecutive": pd.DataFrame()}}
    sections = report_sections(facts, {"ppo_ff": ArtifactRecord("train_ppo", "p", tmp_path)},
                               results, figures, model=model)
    titles = [section.title for section in sections]
    assert titles[0] == "Summary" and titles.count("Summary") == 1, titles
    markdown, page = write_report(tmp_path / "report", "Run", sections)
    text = markdown.read_text()
    assert text.count("## Summary") == 1 and page.read_text().count(">Summary</h2>") == 1
    first = text.split("\n## ")[1]  # the summary, in the order it is read
    printed = first.index("| controller | plant | median_final_mm | within_1mm_% |")
    assert printed < first.index("Dynamics model: **1.00 mm**") < first.index(
        "**simulated arm**") < first.index("| controller | on the learned model [mm] |")


def test_tail_episodes_are_the_arrivals_that_ended_furthest_away():
    distance = np.array([[3.0, 0.9, 2.0],  # arrived, ends at 2.0
                         [3.0, 2.5, 2.8],  # never arrived: left out however far it ends
                         [0.5, 0.5, 1.2],  # arrived, ends at 1.2
                         [2.0, 0.2, 0.3]])  # arrived, ends at 0.3
    assert tail_episodes(distance, count=2).tolist() == [0, 2]
    assert tail_episodes(distance, count=5).tolist() == [0, 2, 3]


def test_after_arrival_figure_draws_each_plant_with_an_arrival(tmp_path):
    goals = np.zeros((2, 3))
    arrives = np.zeros((2, 5, 3))
    arrives[:, :, 0] = np.array([4.0, 0.8, 1.5, 2.0, 2.5]) / 1000  # arrives, drifts away
    never = arrives + np.array([0.01, 0.0, 0.0])  # 10 mm further: never within 1 mm
    commands = np.full((2, 4, 3), 2.0)
    results = {"goals": goals, "paths": {("learned", "ppo_ff", 0): arrives,
                                         ("plant", "ppo_ff", 0): never},
               "commands": {("learned", "ppo_ff", 0): commands,
                            ("plant", "ppo_ff", 0): commands}}
    figure = after_arrival_figure(tmp_path / "after.png", 2.0, results, "ppo_ff")
    assert figure is not None and figure.path.stat().st_size > 10_000
    assert "ended furthest from the goal" in figure.caption
    results["paths"] = {("plant", "ppo_ff", 0): never}
    assert after_arrival_figure(tmp_path / "none.png", 2.0, results, "ppo_ff") is None
