"""report.html: one self-contained page per flight (the plots inlined, the metrics, the mission,
the stack file and the command that flew it), for a browser. `zenpilot fly` copies the mission
and the stack file into the run directory (RUN_FILES) so the page shows what really flew."""

from __future__ import annotations

import base64
import html
import json
from pathlib import Path

REPORT_NAME = "report.html"
RUN_FILES = {"mission": "mission.toml", "stack": "stack.toml", "command": "command.txt"}

_STYLE = """body{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;color:#222}
h1{font-size:1.5em}h2{font-size:1.15em;border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:1.6em}
pre{background:#f6f6f6;padding:.8em;overflow-x:auto;font-size:.85em}img{max-width:100%;display:block;margin:.6em 0}
table{border-collapse:collapse}td{padding:.15em .8em .15em 0;vertical-align:top}
.ok{color:#17702c;font-weight:bold}.bad{color:#b01c1c;font-weight:bold}.note{color:#8a5a00}"""


def _text(path: Path) -> str | None:
    try:
        return path.read_text(errors="replace")
    except OSError:
        return None


def write_report(out: Path, metrics: dict, metrics_table: str, plots: list[Path], log_note: str = "") -> Path:
    """Write out/report.html; returns its path."""
    esc = html.escape
    completed, crashed = metrics.get("completed"), metrics.get("crashed")
    verdict = ('<span class="bad">crashed</span>' if crashed else
               '<span class="ok">completed</span>' if completed else '<span class="bad">not completed</span>')
    facts = [("mission", metrics.get("mission")), ("vehicle", metrics.get("vehicle")), ("mode", metrics.get("mode")),
             ("seed", metrics.get("seed")), ("flown", f"{metrics.get('duration_s', 0.0):.1f} s"),
             ("position RMS", f"{1e3 * metrics['position_rms_m']:.2f} mm" if metrics.get("position_rms_m") is not None
              else "-")]
    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>zenpilot: {esc(str(metrics.get('mission')))}"
             f" ({esc(out.name)})</title><style>{_STYLE}</style></head><body>",
             f"<h1>zenpilot flight {esc(out.name)}: {verdict}</h1>",
             "<table>" + "".join(f"<tr><td>{esc(k)}</td><td>{esc(str(v))}</td></tr>" for k, v in facts) + "</table>"]
    if log_note:
        parts.append(f"<p class='note'>{esc(log_note)}</p>")
    parts.append("<h2>Plots</h2>")
    for p in plots:
        data = base64.b64encode(p.read_bytes()).decode()
        parts.append(f"<img alt='{esc(p.stem)}' src='data:image/png;base64,{data}'>")
    if not plots:
        parts.append("<p>No plot: the log holds none of their messages.</p>")
    parts.append(f"<h2>Metrics</h2><pre>{esc(metrics_table)}</pre>")
    parts.append(f"<details><summary>metrics.json</summary><pre>{esc(json.dumps(metrics, indent=2, sort_keys=True))}"
                 "</pre></details>")
    for title, key in (("Mission", "mission"), ("Stack file", "stack"), ("Command", "command")):
        text = _text(out / RUN_FILES[key])
        parts.append(f"<h2>{title}</h2>" + (f"<pre>{esc(text)}</pre>" if text is not None else
                                            f"<p>Not recorded with this flight ({esc(RUN_FILES[key])}).</p>"))
    parts.append("</body></html>\n")
    path = out / REPORT_NAME
    path.write_text("\n".join(parts))
    return path
