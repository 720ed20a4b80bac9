"""A self-contained HTML report: a results table, plots and per-frame images.

The HTML references image files next to it (relative paths), so the folder can be copied or
served as it is. Tables come in as Markdown pipe tables (the benchmark's ``results.md``) and are
converted to HTML here; no template engine is needed.
"""

from __future__ import annotations

import html
from collections.abc import Sequence
from pathlib import Path

__all__ = ["markdown_tables_to_html", "write_html_report"]

_STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 70em; color: #222; }
table { border-collapse: collapse; margin: 1em 0; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.3em 0.6em; text-align: right; }
th:first-child, td:first-child { text-align: left; }
tr:nth-child(even) { background: #f6f6f6; }
figure { display: inline-block; margin: 0.5em; vertical-align: top; }
figcaption { font-size: 0.85em; color: #555; }
img { max-width: 100%; }
"""


def markdown_tables_to_html(markdown: str) -> str:
    """Convert Markdown text with pipe tables, ``#`` headings and paragraphs to HTML."""
    out: list[str] = []
    lines = markdown.splitlines()
    i = 0
    while i < len(lines):
        line = lines[i].rstrip()
        if line.startswith("|"):
            rows = []
            while i < len(lines) and lines[i].lstrip().startswith("|"):
                cells = [c.strip() for c in lines[i].strip().strip("|").split("|")]
                if not all(set(c) <= set("-: ") for c in cells):
                    rows.append(cells)
                i += 1
            out.append("<table>")
            for r, cells in enumerate(rows):
                tag = "th" if r == 0 else "td"
                out.append(
                    "<tr>" + "".join(f"<{tag}>{html.escape(c)}</{tag}>" for c in cells) + "</tr>"
                )
            out.append("</table>")
            continue
        if line.startswith("#"):
            level = min(len(line) - len(line.lstrip("#")) + 1, 6)
            out.append(f"<h{level}>{html.escape(line.lstrip('#').strip())}</h{level}>")
        elif line.strip():
            out.append(f"<p>{html.escape(line.strip())}</p>")
        i += 1
    return "\n".join(out)


def write_html_report(
    out_dir: str | Path,
    title: str,
    markdown: str,
    plots: Sequence[str | Path] = (),
    frames: Sequence[tuple[str, str | Path]] = (),
    notes: Sequence[str] = (),
) -> Path:
    """Write ``out_dir/report.html``.

    Args:
        title: page title.
        markdown: the results (Markdown with pipe tables).
        plots: image files shown under the table (paths inside ``out_dir``).
        frames: ``(caption, image path)`` per frame image (paths inside ``out_dir``).
        notes: paragraphs shown under the title (the command that made it, etc.).
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)

    def rel(p: str | Path) -> str:
        p = Path(p)
        try:
            return html.escape(str(p.resolve().relative_to(out_dir.resolve())))
        except ValueError:
            return html.escape(str(p))

    parts = [
        "<!DOCTYPE html>",
        f"<html><head><meta charset='utf-8'><title>{html.escape(title)}</title>",
        f"<style>{_STYLE}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        *(f"<p>{html.escape(n)}</p>" for n in notes),
        markdown_tables_to_html(markdown),
    ]
    if plots:
        parts.append("<h2>Plots</h2>")
        parts += [f"<figure><img src='{rel(p)}'></figure>" for p in plots]
    if frames:
        parts.append("<h2>Frames: estimates against the truth (white)</h2>")
        parts += [
            f"<figure><img src='{rel(p)}'><figcaption>{html.escape(c)}</figcaption></figure>"
            for c, p in frames
        ]
    parts.append("</body></html>")
    path = out_dir / "report.html"
    path.write_text("\n".join(parts), encoding="utf-8")
    return path
