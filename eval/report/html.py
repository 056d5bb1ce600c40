"""The report page: a self-contained HTML document (inline CSS, images as base64 PNG, no scripts, no
network), assembled from sections."""

from __future__ import annotations

import base64
import html
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',Roboto,sans-serif;margin:24px auto;max-width:1400px;
     color:#222;padding:0 16px}
h1{font-size:1.6em;margin-bottom:0.2em} h2{font-size:1.3em;border-bottom:2px solid #4477aa;padding-bottom:4px;
margin-top:2em} h3{font-size:1.05em;margin-top:1.4em}
table{border-collapse:collapse;margin:8px 0 16px 0;font-size:0.92em}
th,td{border:1px solid #ccc;padding:3px 8px;text-align:right} th{background:#eef2f7}
td:first-child,th:first-child{text-align:left}
img{max-width:100%;height:auto;border:1px solid #ddd}
.strip{display:flex;flex-wrap:wrap;gap:8px} .strip figure{margin:0} figcaption{font-size:0.85em;color:#555}
pre{background:#f6f8fa;border:1px solid #ddd;padding:8px;overflow-x:auto;font-size:0.85em;white-space:pre-wrap}
.note{color:#777;font-style:italic} .failed{color:#cc3311;font-weight:bold} .ok{color:#228833}
nav a{margin-right:12px}
"""


@dataclass
class Section:
    id: str
    title: str
    parts: list[str] = field(default_factory=list)

    def add(self, *html_parts: str) -> Section:
        self.parts.extend(html_parts)
        return self


def esc(text: object) -> str:
    return html.escape(str(text), quote=True)


def table(header: Sequence[object], rows: Iterable[Sequence[object]], cls: dict[int, str] | None = None) -> str:
    head = "".join(f"<th>{esc(h)}</th>" for h in header)
    body = []
    for r in rows:
        body.append("<tr>" + "".join(f"<td>{esc(c)}</td>" for c in r) + "</tr>")
    return f"<table><thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table>"


def image(png: bytes, alt: str, width: int | None = None) -> str:
    w = f' width="{int(width)}"' if width else ""
    return f'<img alt="{esc(alt)}"{w} src="data:image/png;base64,{base64.b64encode(png).decode("ascii")}">'


def note(text: str) -> str:
    return f'<p class="note">{esc(text)}</p>'


def pre(text: str) -> str:
    return f"<pre>{html.escape(text, quote=False)}</pre>"


def page(title: str, subtitle: str, sections: list[Section]) -> str:
    nav = " ".join(f'<a href="#{esc(s.id)}">{esc(s.title)}</a>' for s in sections)
    body = "\n".join(f'<section id="{esc(s.id)}"><h2>{esc(s.title)}</h2>\n' + "\n".join(s.parts) + "</section>"
                     for s in sections)
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\"><link rel=\"icon\" href=\"data:,\">"
            f"<title>{esc(title)}</title><style>{CSS}</style></head><body>"
            f"<h1>{esc(title)}</h1><p>{esc(subtitle)}</p><nav>{nav}</nav>\n{body}\n</body></html>\n")
