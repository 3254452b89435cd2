"""Self-contained report.html: every figure inlined as base64 PNG, the paper comparison table, config, versions."""

from __future__ import annotations

import base64
import html
import json
from pathlib import Path

from needletissue.report.config import annotated_toml
from needletissue.runinfo import relocate, version_record, write_atomic

_CSS = """
body{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;color:#222}
table{border-collapse:collapse;margin:1em 0;font-size:0.92em;display:block;max-width:100%;overflow-x:auto}
th,td{border:1px solid #bbb;padding:4px 8px;text-align:right}
th{background:#eee} td.l,th.l{text-align:left}
.ok{color:#080}.failed{color:#b00}.skipped{color:#777}
img{max-width:100%;border:1px solid #ddd;margin:4px 0}
pre{background:#f6f6f6;padding:8px;overflow-x:auto;font-size:0.85em}
figure{display:block;margin:1.2em 0;max-width:100%}
figure img{width:100%;height:auto;display:block}
figcaption{font-size:0.9em;color:#333;margin-top:4px;overflow-wrap:anywhere}
figcaption code{color:#666}
"""


def _fmt(v, digits=4):
    if v is None:
        return "—"
    if isinstance(v, float):
        return f"{v:.{digits}g}"
    return html.escape(str(v))


def _img(path: Path) -> str:
    """A figure at the column's full width, captioned by what it shows (the PNG's Description) and its file."""
    from needletissue.report.render import caption

    data = base64.b64encode(Path(path).read_bytes()).decode()
    name = html.escape(Path(path).name)
    text = html.escape(caption(path))
    cap = f"{text} <code>{name}</code>" if text else f"<code>{name}</code>"
    return (f'<figure><img alt="{text or name}" src="data:image/png;base64,{data}">'
            f"<figcaption>{cap}</figcaption></figure>")


def comparison_table(result) -> str:
    rows = [c for o in result.outcomes if o.result for c in o.result.comparisons]
    if not rows:
        return "<p>No stage produced a number the paper reports.</p>"
    out = ['<table><tr><th class="l">quantity</th><th>ours</th><th>paper</th><th>difference</th>'
           '<th>difference %</th><th class="l">unit</th><th class="l">verdict</th>'
           '<th class="l">paper source / note</th></tr>']
    for c in rows:
        j = c.to_json()
        src = " — ".join(x for x in (j["paper_source"], c.note) if x)
        out.append(f'<tr><td class="l">{html.escape(c.quantity)}</td><td>{_fmt(c.ours)}</td>'
                   f'<td>{_fmt(j["paper"])}</td><td>{_fmt(j["difference"], 3)}</td>'
                   f'<td>{_fmt(j["relative_difference_percent"], 3)}</td><td class="l">{html.escape(c.unit)}</td>'
                   f'<td class="l">{html.escape(j["verdict"])}</td>'
                   f'<td class="l">{html.escape(src)}</td></tr>')
    out.append("</table>")
    return "\n".join(out)


def _md(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v).replace("|", "\\|")


def comparison_markdown(rows: list[dict]) -> str:
    """The comparison with the paper as a Markdown table, from results.json's `comparison_with_paper`
    (the README's table is this text from a `make demo` run, checked by tests/test_readme.py)."""
    out = ["| quantity | this toolkit | paper | verdict | note |", "|---|---|---|---|---|"]
    for r in rows:
        unit = f" {r['unit']}" if r["unit"] and r["ours"] is not None and not isinstance(r["ours"], str) else ""
        paper = "-" if r["paper"] is None else f"{_md(r['paper'])}{unit}"
        note = " — ".join(x for x in (r.get("paper_source"), r.get("note")) if x)
        out.append(f"| {_md(r['quantity'])} | {_md(r['ours'])}{unit} | {paper} | {_md(r.get('verdict') or '-')} "
                   f"| {_md(note or '-')} |")
    return "\n".join(out) + "\n"


def write_report(run_dir: Path, cfg, result) -> Path:
    from needletissue.report.viewer import page_head, viewer_html

    has_views = any(o.result and o.result.views for o in result.outcomes)
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><meta name='viewport' "
             f"content='width=device-width, initial-scale=1'><title>needletissue reproduce</title>"
             f"<style>{_CSS}</style>{page_head() if has_views else ''}</head><body>",
             "<h1>needletissue: reproduction of the reference study</h1>",
             "<p>Units: mm, N, MPa, s. Paper: <i>Study on the interactive deformation of bone needles and "
             "circum-pelvic soft tissue</i>. Every number below was computed by this run; the paper column "
             "holds the values printed in the paper.</p>",
             "<h2>Stages</h2><table><tr><th class='l'>stage</th><th class='l'>status</th><th>time (s)</th>"
             "<th class='l'>note</th></tr>"]
    for o in result.outcomes:
        reason = html.escape(o.reason.splitlines()[0]) if o.reason else ""
        parts.append(f"<tr><td class='l'>{html.escape(o.title)}</td><td class='l {o.status}'>{o.status}</td>"
                     f"<td>{o.wall_time_s:.1f}</td><td class='l'>{reason}</td></tr>")
    parts.append(f"</table><p>Total wall time {result.wall_time_s:.1f} s.</p>")
    parts.append("<h2>Reproduced numbers beside the paper</h2>")
    parts.append(comparison_table(result))
    for o in result.outcomes:
        parts.append(f"<h2>{html.escape(o.title)} <small class='{o.status}'>({o.status})</small></h2>")
        if o.status == "failed":
            parts.append(f"<pre>{html.escape(o.reason)}</pre>")
        if o.result is None:
            if o.status == "skipped":
                parts.append(f"<p>{html.escape(o.reason)}</p>")
            continue
        for note in o.result.notes:
            parts.append(f"<p>{html.escape(note)}</p>")
        parts.extend(_img(p) for p in o.result.figures if Path(p).suffix == ".png")
        parts.extend(viewer_html(scene, title) for title, scene in o.result.views)
        if o.result.files:
            names = ", ".join(html.escape(str(Path(p).relative_to(run_dir))) for p in o.result.files)
            parts.append(f"<p>Files: {names}</p>")
        data = json.dumps(relocate(o.result.data, run_dir), indent=1)
        if len(data) < 20000:
            parts.append(f"<details><summary>result data</summary><pre>{html.escape(data)}</pre></details>")
    parts.append(f"<h2>Configuration</h2><pre>{html.escape(annotated_toml(cfg))}</pre>")
    parts.append(f"<h2>Versions</h2><pre>{html.escape(json.dumps(version_record(), indent=1))}</pre>")
    parts.append("</body></html>")
    return write_atomic(run_dir / "report.html", "\n".join(parts))
