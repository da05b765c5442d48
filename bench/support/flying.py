"""`zenpilot fly` as the benches run it: the flight's progress shown as it flies, its output kept.

`fly` prints a progress line (simulated time, wall time, speed, the mission's bar) every 10 s when
its output is not a terminal; here each one goes to the bench's stderr under the flight's label
(redrawn in place on a terminal), so a bench of many flights says where it is without mixing
into the table it prints on stdout.
"""
from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def fly(args: list[str], label: str, cwd: Path = ROOT) -> subprocess.CompletedProcess:
    """Run `python -m deploy.cli fly ARGS`; returns it as subprocess.run(capture_output=True,
    text=True) would (stderr folded into stdout)."""
    argv = [sys.executable, "-m", "deploy.cli", "fly", *args]
    tty = sys.stderr.isatty()
    t0 = time.monotonic()
    show(f"{label}: starting", tty)
    kept = []
    with subprocess.Popen(argv, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) as proc:
        for line in proc.stdout:
            kept.append(line)
            if line.startswith("sim "):   # deploy/progress.py's line
                show(f"{label}: {line.strip()}", tty)
    show(f"{label}: done in {time.monotonic() - t0:.1f} s (status {proc.returncode})", tty, last=True)
    return subprocess.CompletedProcess(argv, proc.returncode, "".join(kept), "")


def show(text: str, tty: bool, last: bool = False) -> None:
    if tty:
        sys.stderr.write("\r\033[K" + text + ("\n" if last else ""))
    else:
        sys.stderr.write(text + "\n")
    sys.stderr.flush()
