"""Markdown tables from the JSON lines written by ``model_search.py``.

    .venv/bin/python -m experiments.model_report outputs/model_search/final_*.jsonl
"""

from __future__ import annotations

import json
import sys

import pandas as pd


def to_markdown(frame: pd.DataFrame, float_format: str = "{:.2f}") -> str:
    """A pipe table (pandas' ``to_markdown`` needs the optional ``tabulate``)."""

    def text(value):
        return float_format.format(value) if isinstance(value, float) else str(value)

    header = [frame.index.name or "", *map(str, frame.columns)]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for index, row in frame.iterrows():
        lines.append("| " + " | ".join([str(index), *map(text, row.tolist())]) + " |")
    return "\n".join(lines)


def main(paths: list[str]) -> None:
    rows = [json.loads(line) for path in paths for line in open(path) if line.strip()]
    frame = pd.DataFrame(rows)
    frame["run"] = frame["held_out"].str.replace("Step_control_", "", regex=False)
    cell = frame["mean_mm"].map("{:.2f}".format) + " / " + frame["p95_mm"].map("{:.2f}".format)
    frame["model"] = cell
    table = frame.pivot_table(index="run", columns="tag", values="model", aggfunc="first")
    first = frame.drop_duplicates("run").set_index("run")
    table["linear lagged"] = (first["baseline_linear_mm"].map("{:.2f}".format) + " / "
                              + first["baseline_linear_p95_mm"].map("{:.2f}".format))
    table["mean position"] = (first["baseline_mean_mm"].map("{:.2f}".format) + " / "
                              + first["baseline_mean_p95_mm"].map("{:.2f}".format))
    print("mean / p95 open-loop error [mm], each run held out once (train on the other six)\n")
    print(to_markdown(table))
    averages = frame.groupby("tag")[["mean_mm", "p95_mm", "train_s", "train_cpu_s"]].mean()
    averages.loc["linear lagged", ["mean_mm", "p95_mm"]] = [
        first["baseline_linear_mm"].mean(), first["baseline_linear_p95_mm"].mean()]
    averages.loc["mean position", ["mean_mm", "p95_mm"]] = [
        first["baseline_mean_mm"].mean(), first["baseline_mean_p95_mm"].mean()]
    print("\naverage over the 7 folds\n")
    print(to_markdown(averages))


if __name__ == "__main__":
    main(sys.argv[1:])
