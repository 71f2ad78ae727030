"""Small HTML helpers for a self-contained report: escaped tables and sections, the inline style sheet."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from html import escape
from typing import Any


class Raw(str):
    """Markup inserted as is (already escaped)."""


def esc(x: Any) -> str:
    return x if isinstance(x, Raw) else escape("" if x is None else str(x), quote=True)


def mm(v: float | None, digits: int = 3, sign: bool = False) -> str:
    """Metres shown in mm ('-' when missing)."""
    if v is None:
        return "-"
    return f"{v * 1e3:{'+' if sign else ''}.{digits}f}"


def num(v: float | None, fmt: str = ".3f") -> str:
    return "-" if v is None else format(v, fmt)


def table(
    headers: Sequence[Any],
    rows: Iterable[Sequence[Any]],
    *,
    caption: str | None = None,
    cls: str = "data",
    first_col_header: bool = True,
) -> Raw:
    """An HTML table; every cell escaped unless it is :class:`Raw`."""
    out = [f'<table class="{esc(cls)}">']
    if caption:
        out.append(f"<caption>{esc(caption)}</caption>")
    out.append("<thead><tr>" + "".join(f"<th>{esc(h)}</th>" for h in headers) + "</tr></thead><tbody>")
    for row in rows:
        cells = []
        for i, c in enumerate(row):
            tag = "th" if (i == 0 and first_col_header) else "td"
            cells.append(f"<{tag}>{esc(c)}</{tag}>")
        out.append("<tr>" + "".join(cells) + "</tr>")
    out.append("</tbody></table>")
    return Raw("".join(out))


def kv_table(rows: Iterable[tuple[Any, Any]], cls: str = "kv") -> Raw:
    """A two-column item/value table."""
    return Raw(
        f'<table class="{esc(cls)}"><tbody>'
        + "".join(f"<tr><th>{esc(k)}</th><td>{esc(v)}</td></tr>" for k, v in rows)
        + "</tbody></table>"
    )


def figure(uri: str | None, alt: str, caption: str) -> Raw:
    if uri is None:
        return Raw(f'<p class="note">{esc(caption)}: nothing to plot.</p>')
    return Raw(f'<figure><img src="{esc(uri)}" alt="{esc(alt)}"><figcaption>{esc(caption)}</figcaption></figure>')


def section(ident: str, title: str, *parts: Any) -> Raw:
    body = "".join(p if isinstance(p, Raw) else f"<p>{esc(p)}</p>" for p in parts if p is not None)
    return Raw(f'<section id="{esc(ident)}"><h2>{esc(title)}</h2>{body}</section>')


def bullet_list(items: Iterable[Any]) -> Raw:
    return Raw("<ul>" + "".join(f"<li>{esc(i)}</li>" for i in items) + "</ul>")


CSS = """
:root { --ink: #1b1b1b; --rule: #b9b9b9; --head: #eef1f5; --accent: #1f4e79; }
* { box-sizing: border-box; }
body { font: 14px/1.45 "DejaVu Sans", "Helvetica Neue", Arial, sans-serif; color: var(--ink); margin: 0;
       background: #f6f6f4; }
main { max-width: 1120px; margin: 0 auto; padding: 24px 32px 48px; background: white; }
header.title { border-bottom: 3px double var(--accent); margin-bottom: 16px; }
h1 { font-family: "DejaVu Serif", Georgia, serif; font-size: 26px; color: var(--accent); margin: 8px 0 4px; }
h2 { font-family: "DejaVu Serif", Georgia, serif; font-size: 19px; color: var(--accent);
     border-bottom: 1px solid var(--rule); padding-bottom: 3px; margin-top: 32px; }
h3 { font-size: 15px; margin: 18px 0 6px; }
table { border-collapse: collapse; margin: 8px 0 14px; font-variant-numeric: tabular-nums; }
caption { caption-side: top; text-align: left; font-weight: bold; padding: 4px 0; }
th, td { border: 1px solid var(--rule); padding: 3px 8px; vertical-align: top; }
thead th { background: var(--head); }
table.data td { text-align: right; white-space: nowrap; }
table.data tbody th { text-align: left; font-weight: normal; background: #fafafa; }
table.kv th { text-align: left; background: var(--head); font-weight: normal; width: 16em; }
table.kv td { font-family: "DejaVu Sans Mono", monospace; font-size: 13px; word-break: break-all; }
table.wide td { white-space: normal; text-align: left; }
figure { margin: 10px 0 18px; }
figure img { max-width: 100%; height: auto; border: 1px solid #ddd; display: block; }
figcaption { font-size: 12px; color: #444; margin-top: 4px; }
.note { color: #555; font-size: 13px; }
.frames figure { display: inline-block; width: 100%; }
.missing li { color: #7a3b00; }
.verdict { border-left: 5px solid #2ca02c; background: #eef8ee; padding: 4px 14px; margin: 12px 0; }
.verdict.none { border-color: #b00; background: #fbeeee; }
nav ol { columns: 2; font-size: 13px; }
footer { margin-top: 40px; font-size: 12px; color: #555; border-top: 1px solid var(--rule); padding-top: 8px; }
@media print { body { background: white; } main { padding: 0; } section { break-inside: avoid-page; } }
"""


def page(title: str, body: Sequence[str]) -> str:
    """The whole document: inline CSS, no script, no external reference."""
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f'<title>{esc(title)}</title><meta name="viewport" content="width=device-width, initial-scale=1">'
        f"<style>{CSS}</style></head><body><main>" + "".join(body) + "</main></body></html>\n"
    )
