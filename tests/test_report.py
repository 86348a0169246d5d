"""The report writer lays out text, tables and figures in Markdown and HTML."""

from __future__ import annotations

import pandas as pd

from pipeline.evaluation.report import Figure, Section, Table, write_report


def test_report_has_every_section_table_and_figure(tmp_path):
    figure = tmp_path / "artifacts" / "fig.png"
    figure.parent.mkdir()
    figure.write_bytes(b"\x89PNG")
    sections = [
        Section("Configuration", ["Robot `sim`, **4** runs.", "```yaml\na: 1\n```"]),
        Section("Results", [Table(pd.DataFrame({"policy": ["ff", "a|b"], "mm": [0.51234, None]}),
                                  "final distance"), Figure(figure, "a figure")]),
    ]
    md, page = write_report(tmp_path / "report", "Run", sections)
    text = md.read_text()
    assert "## Configuration" in text and "## Results" in text
    assert "| policy | mm |" in text and "| ff | 0.512 |" in text and "a\\|b" in text
    assert "![a figure](../artifacts/fig.png)" in text
    markup = page.read_text()
    assert "<code>sim</code>" in markup and "<b>4</b>" in markup
    assert "src='../artifacts/fig.png'" in markup and "<pre>" in markup
    assert markup.count("<h2") == 2 and "<details>" in markup
