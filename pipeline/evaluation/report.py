"""A run report as Markdown and as a static HTML page, from sections of text, tables and figures.

The evaluate stage assembles the sections; this module only lays them out. Figures are linked by
paths relative to the report, so the report and the artifacts it links stay together.
"""

from __future__ import annotations

import html
import os
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

_CSS = """
body { font-family: -apple-system, 'Segoe UI', Helvetica, Arial, sans-serif; max-width: 1100px;
       margin: 2em auto; padding: 0 1.2em; color: #1f2328; line-height: 1.45; }
h1 { border-bottom: 2px solid #d0d7de; padding-bottom: .3em; }
h2 { border-bottom: 1px solid #d0d7de; padding-bottom: .2em; margin-top: 1.8em; }
table { border-collapse: collapse; margin: .8em 0; font-size: 0.9em; }
th, td { border: 1px solid #d0d7de; padding: 4px 9px; text-align: right; }
th { background: #f6f8fa; }
td:first-child, th:first-child { text-align: left; }
figure { margin: 1em 0; }
figure img { max-width: 100%; border: 1px solid #d0d7de; }
figcaption { font-size: 0.9em; color: #57606a; }
pre { background: #f6f8fa; padding: .8em; overflow-x: auto; font-size: 0.85em; }
.note { color: #57606a; font-size: 0.9em; }
.scroll { overflow-x: auto; }
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
    float_format: str = "{:.3g}"


@dataclass
class Section:
    title: str
    blocks: list[str | Table | Figure] = field(default_factory=list)

    def add(self, block: str | Table | Figure) -> Section:
        self.blocks.append(block)
        return self


def _relative(path: Path, base: Path) -> str:
    return os.path.relpath(Path(path).resolve(), base.resolve())


def _format(frame: pd.DataFrame, float_format: str) -> pd.DataFrame:
    def cell(value):
        if isinstance(value, float):
            return "–" if pd.isna(value) else float_format.format(value)
        return value

    return frame.map(cell)


def _markdown_table(frame: pd.DataFrame) -> str:
    def row(cells) -> str:
        return "| " + " | ".join(str(c).replace("|", "\\|") for c in cells) + " |"

    lines = [row(frame.columns), row(["---"] * len(frame.columns))]
    lines += [row(values) for values in frame.itertuples(index=False)]
    return "\n".join(lines)


def render_markdown(title: str, sections: list[Section], base: Path) -> str:
    lines = [f"# {title}", ""]
    for section in sections:
        lines += [f"## {section.title}", ""]
        for block in section.blocks:
            if isinstance(block, Table):
                if block.caption:
                    lines += [f"*{block.caption}*", ""]
                lines += [_markdown_table(_format(block.frame, block.float_format)), ""]
            elif isinstance(block, Figure):
                lines += [f"![{block.caption}]({_relative(block.path, base)})", "",
                          f"*{block.caption}*", ""]
            else:
                lines += [block, ""]
    return "\n".join(lines)


def render_html(title: str, sections: list[Section], base: Path) -> str:
    body = [f"<h1>{html.escape(title)}</h1>"]
    toc = "".join(f'<li><a href="#s{i}">{html.escape(s.title)}</a></li>'
                  for i, s in enumerate(sections))
    body.append(f"<ul>{toc}</ul>")
    for i, section in enumerate(sections):
        body.append(f'<h2 id="s{i}">{html.escape(section.title)}</h2>')
        for block in section.blocks:
            if isinstance(block, Table):
                table = _format(block.frame, block.float_format).to_html(index=False,
                                                                         border=0, escape=True)
                caption = f"<p class='note'>{html.escape(block.caption)}</p>" if block.caption \
                    else ""
                body.append(f"{caption}<div class='scroll'>{table}</div>")
            elif isinstance(block, Figure):
                body.append(f"<figure><img src='{html.escape(_relative(block.path, base))}' "
                            f"alt='{html.escape(block.caption)}'><figcaption>"
                            f"{html.escape(block.caption)}</figcaption></figure>")
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
    page.write_text(render_html(title, sections, folder))
    return markdown, page
