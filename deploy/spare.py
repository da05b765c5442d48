"""A warm spare for the supervisor's restarts (deploy/supervisor.py): a process that has already
imported what every service imports (numpy, Zenoh, the codec, the runtime: ~0.4 s of a service's
~0.5 s start-up on this machine) and waits on its standard input for the service it is to become.

The launcher writes one line of JSON, {"module": "services.motors", "argv": [...], "log": path};
the spare points its output at the service's log and runs the module as `python -m` would. An
empty input (the launcher gone) ends it. A vehicle whose motor driver died holds its last PWM and
tilts 20 degrees in half a second: the restart cannot wait for imports.
"""
from __future__ import annotations

import json
import os
import runpy
import sys


def main() -> None:
    import numpy  # noqa: F401  (imported ahead: the point of a spare)
    import zenoh  # noqa: F401

    import schemas  # noqa: F401
    import services.runtime  # noqa: F401
    line = sys.stdin.readline()
    if not line.strip():
        return   # not needed after all
    job = json.loads(line)
    log = os.open(job["log"], os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    os.dup2(log, 1)
    os.dup2(log, 2)
    os.close(log)
    devnull = os.open(os.devnull, os.O_RDONLY)
    os.dup2(devnull, 0)
    os.close(devnull)
    sys.argv = [job["module"], *job["argv"]]
    runpy.run_module(job["module"], run_name="__main__", alter_sys=True)


if __name__ == "__main__":
    main()
