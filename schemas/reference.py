"""Generate the message reference page: `python -m schemas.reference > docs/messages.md`."""

from __future__ import annotations

import sys

from .core import HEADER_FIELDS, REASONS
from .messages import ALL, __doc__ as MESSAGES_DOC


def _row(f) -> str:
    kind = f.kind + (f"[{f.length}]" if f.length and f.kind.endswith("[]") else "")
    kind = kind.replace("[][", "[")
    rng = ""
    if f.choices:
        rng = " / ".join(f"`{c}`" for c in f.choices)
    elif f.min is not None or f.max is not None:
        lo = "-inf" if f.min is None else f"{f.min:g}"
        hi = "inf" if f.max is None else f"{f.max:g}"
        rng = f"[{lo}, {hi}]"
    return f"| `{f.name}` | {kind} | {f.unit or ''} | {rng} | {f.doc} |"


def render() -> str:
    out = [
        "# zenpilot message reference",
        "",
        "Generated from `schemas/messages.py` by `python -m schemas.reference`; do not edit by hand.",
        "",
        (MESSAGES_DOC or "").strip(),
        "",
        "## Wire format",
        "",
        "Every message is one MessagePack map (decode it with any MessagePack library):",
        "",
        "    {\"version\": int, \"header\": {\"t_s\": float, \"seq\": int, \"source\": str}, <fields>}",
        "",
        "| header field | type | unit | range | meaning |",
        "|---|---|---|---|---|",
        *[_row(f) for f in HEADER_FIELDS],
        "",
        "`float` fields accept MessagePack integers too. Receivers reject a message with a "
        "missing or extra field, a wrong type or array length, NaN/Inf, a value outside its "
        "range or another version; they count it under one of these reasons and drop it: "
        + ", ".join(f"`{r}`" for r in REASONS) + ".",
        "",
        "## Key expressions",
        "",
        "Priority: `control` keys travel at Zenoh's real-time priority, all at one so that their order "
        "on a link holds (a plan before its setpoint, a run's outputs before its sync); `bulk` keys at "
        "the background priority, in a queue of their own, so that a flood of them never holds a "
        "control message up on a shared link (docs/reliability.md). Real time: `reliable` keys "
        "(what must arrive, and bulk) are sent reliably; `stream` keys best effort, where the next sample "
        "replaces a lost one, so that across a link they can take an unreliable (UDP) link and never wait "
        "behind a lost one's retransmission. Lockstep sends every key reliably.",
        "",
        "| key expression | message | version | priority | real time |",
        "|---|---|---|---|---|",
        *[f"| `{m.key('<vehicle>', '<service>')}` | [{m.name}](#{m.name}) | {m.version} | {m.priority} | "
          f"{'reliable' if m.sent_reliably else 'stream'} |" for m in ALL],
        "| `zp/<vehicle>/alive/<service>` | liveliness token | | | |",
        "",
    ]
    for m in ALL:
        out += [
            f"## {m.name}",
            "",
            f"Key `{m.key('<vehicle>', '<service>')}`, version {m.version}. {m.doc}",
            "",
            "| field | type | unit | range | meaning |",
            "|---|---|---|---|---|",
            *[_row(f) for f in m.fields],
            "",
        ]
    return "\n".join(out)


if __name__ == "__main__":
    sys.stdout.write(render())
