"""A run report as Markdown and as a static HTML page, from sections of text, tables and figures.

The evaluate stage assembles the sections (:mod:`pipeline.evaluation.sections`); this module only
lays them out. The HTML page is self-contained: every figure is embedded as a base64 data URI, so
the page keeps its pictures wherever it is copied. The Markdown links copies of the figures in
``figures/`` beside it (figures of other artifacts are copied there).

Numbers are shown with three significant figures (trailing zeros kept: 0.470 beside 0.567),
``inf`` as ∞ and missing values as –.
"""

from __future__ import annotations

import base64
import html
import math
import mimetypes
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

_CSS = """
body { font-family: -apple-system, 'Segoe UI', Helvetica, Arial, sans-serif; max-width: 1500px;
       margin: 2em auto; padding: 0 1.2em; color: #1f2328; line-height: 1.45; }
p, ul, figcaption, .note { max-width: 1000px; }
h1 { border-bottom: 2px solid #d0d7de; padding-bottom: .3em; }
h2 { border-bottom: 1px solid #d0d7de; padding-bottom: .2em; margin-top: 1.8em; }
table { border-collapse: collapse; margin: .8em 0; font-size: 0.88em; }
th, td { border: 1px solid #d0d7de; padding: 4px 8px; text-align: right; }
th { background: #f6f8fa; max-width: 8.5em; vertical-align: bottom; font-weight: 600; }
td { white-space: nowrap; font-variant-numeric: tabular-nums; }
td:first-child, th:first-child { text-align: left; }
figure { margin: 1em 0; }
figure img { max-width: 100%; border: 1px solid #d0d7de; }
figcaption { font-size: 0.9em; color: #57606a; }
pre { background: #f6f8fa; padding: .8em; overflow-x: auto; font-size: 0.85em; }
.note { color: #57606a; font-size: 0.9em; }
.scroll { overflow-x: auto; max-width: 100%; }
summary { cursor: pointer; color: #0969da; }
"""


@dataclass
class Figure:
    path: Path
    caption: str


@dataclass
class Table:
    frame: pd.DataFrame
    caption: str = ""
    significant: int = 3


@dataclass
class Section:
    title: str
    blocks: list[str | Table | Figure] = field(default_factory=list)

    def add(self, block: str | Table | Figure) -> Section:
        self.blocks.append(block)
        return self


def format_number(value: float, significant: int = 3) -> str:
    """``value`` with ``significant`` significant figures, trailing zeros kept (0.470, 12.0,
    1.00e-05); whole numbers of 10**significant and more without decimals (12,345)."""
    if math.isnan(value):
        return "–"
    if math.isinf(value):
        return "∞" if value > 0 else "−∞"
    if value == 0:
        return "0"
    if abs(value) >= 10 ** significant:
        return f"{value:,.0f}"
    text = f"{value:#.{significant}g}"
    return text.rstrip(".") if "e" not in text else text


def _format(frame: pd.DataFrame, significant: int) -> pd.DataFrame:
    def cell(value):
        if isinstance(value, (bool, np.bool_)):
            return "yes" if value else "no"
        if isinstance(value, (float, np.floating)):
            return format_number(float(value), significant)
        return "–" if value is None else value

    return frame.astype(object).map(cell)


def _markdown_table(frame: pd.DataFrame) -> str:
    def row(cells) -> str:
        return "| " + " | ".join(str(c).replace("|", "\\|") for c in cells) + " |"

    lines = [row(frame.columns), row(["---"] * len(frame.columns))]
    lines += [row(values) for values in frame.itertuples(index=False)]
    return "\n".join(lines)


def _html_table(frame: pd.DataFrame) -> str:
    """A plain HTML table; header names may wrap after an underscore or a space."""
    def header(name) -> str:
        return html.escape(str(name)).replace("_", "_<wbr>")

    head = "".join(f"<th>{header(c)}</th>" for c in frame.columns)
    rows = "".join("<tr>" + "".join(f"<td>{html.escape(str(v))}</td>" for v in values) + "</tr>"
                   for values in frame.itertuples(index=False))
    return f"<table><thead><tr>{head}</tr></thead><tbody>{rows}</tbody></table>"


def data_uri(path: Path) -> str:
    """The file as a ``data:`` URI (base64), for a page that needs no other file."""
    mime = mimetypes.guess_type(str(path))[0] or "application/octet-stream"
    return f"data:{mime};base64,{base64.b64encode(Path(path).read_bytes()).decode('ascii')}"


def _local_copy(path: Path, folder: Path) -> str:
    """The link of ``path`` from a report in ``folder``: a file inside ``folder`` as it is, any
    other copied into ``folder/figures/`` (the report and its figures travel together)."""
    path, folder = Path(path).resolve(), Path(folder).resolve()
    if not path.is_relative_to(folder):
        target = folder / "figures" / f"{path.parent.parent.name}-{path.name}"
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(path, target)
        path = target
    return path.relative_to(folder).as_posix()


def render_markdown(title: str, sections: list[Section], base: Path) -> str:
    """The report as Markdown; figures outside ``base`` are copied into ``base/figures/``."""
    lines = [f"# {title}", ""]
    for section in sections:
        lines += [f"## {section.title}", ""]
        for block in section.blocks:
            if isinstance(block, Table):
                if block.caption:
                    lines += [f"*{block.caption}*", ""]
                lines += [_markdown_table(_format(block.frame, block.significant)), ""]
            elif isinstance(block, Figure):
                lines += [f"![{block.caption}]({_local_copy(block.path, base)})", "",
                          f"*{block.caption}*", ""]
            else:
                lines += [block, ""]
    return "\n".join(lines)


def render_html(title: str, sections: list[Section]) -> str:
    """The report as one self-contained HTML page (figures embedded)."""
    body = [f"<h1>{html.escape(title)}</h1>"]
    toc = "".join(f'<li><a href="#s{i}">{html.escape(s.title)}</a></li>'
                  for i, s in enumerate(sections))
    body.append(f"<ul>{toc}</ul>")
    for i, section in enumerate(sections):
        body.append(f'<h2 id="s{i}">{html.escape(section.title)}</h2>')
        for block in section.blocks:
            if isinstance(block, Table):
                table = _html_table(_format(block.frame, block.significant))
                caption = f"<p class='note'>{_inline(block.caption)}</p>" if block.caption \
                    else ""
                body.append(f"{caption}<div class='scroll'>{table}</div>")
            elif isinstance(block, Figure):
                body.append(f"<figure><img src='{data_uri(block.path)}' "
                            f"alt='{html.escape(block.caption)}'><figcaption>"
                            f"{_inline(block.caption)}</figcaption></figure>")
            elif block.startswith("```"):
                # long listings (the full configuration) stay folded until asked for
                code = block.strip("`").split("\n", 1)[-1]
                body.append(f"<details><summary>show</summary><pre>{html.escape(code)}</pre>"
                            "</details>")
            else:
                body.append(f"<p>{_inline(block)}</p>")
    return (f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}"
            f"</title><style>{_CSS}</style></head><body>{''.join(body)}</body></html>")


def _inline(text: str) -> str:
    """Escape text, keeping Markdown's **bold** and `code` spans readable in HTML."""
    escaped = html.escape(text)
    parts = escaped.split("`")
    escaped = "".join(f"<code>{p}</code>" if i % 2 else p for i, p in enumerate(parts))
    parts = escaped.split("**")
    return "".join(f"<b>{p}</b>" if i % 2 else p for i, p in enumerate(parts))


def write_report(folder: Path, title: str, sections: list[Section]) -> tuple[Path, Path]:
    """Write ``report.md`` and ``report.html`` into ``folder``; return both paths."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    markdown = folder / "report.md"
    page = folder / "report.html"
    markdown.write_text(render_markdown(title, sections, folder))
    page.write_text(render_html(title, sections))
    return markdown, page
