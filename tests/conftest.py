"""How the suite runs on three workers (pytest-xdist, `-n 3 --dist loadgroup` in pyproject.toml).

Tests marked `realtime` fly on the wall clock: they run one at a time, all on one worker, first.
Every other test runs at the OS's idle scheduling class (SCHED_IDLE, its processes too), so it
takes only the CPU a real-time flight leaves: the stack's loops run SCHED_FIFO, its router and
tools at normal priority, and each wakes ahead of idle work (under a lockstep flight or a JAX
compile at normal priority on the other core, a real-time stack's timing is not what the test
judges). Two workers beside the real-time one: a real-time stack uses a third to two thirds of a
core, and one idle worker could take only one of the two cores, the rest of the machine idle for
the real-time group's minutes. The integration tests that share a flight come next, then the unit
modules, then the other integration tests. A unit module stays on one worker (its module
fixtures: an iLQR solver compiled once), and so do the integration tests that read one module- or
session-scoped flight (flown once, not once per worker).
"""

import os
import warnings

import pytest

from deploy.launcher import SERVICE_THREADS

# One BLAS thread in every process of the suite, as the launcher gives the services: set before a
# test module loads numpy, and inherited by the commands the tests run (`zenpilot ...`, benches).
# OpenBLAS otherwise starts a thread per core in each of them, ~0.1 s of CPU per process.
for _key, _value in SERVICE_THREADS.items():
    os.environ.setdefault(_key, _value)

REALTIME = "realtime"
UNDER_XDIST = "PYTEST_XDIST_TESTRUNUID" in os.environ


def pytest_itemcollected(item):   # as collected: xdist names the groups before other hooks see the items
    if item.get_closest_marker(REALTIME):
        item.add_marker(pytest.mark.xdist_group(REALTIME))
    elif item.nodeid.startswith("tests/unit/"):
        item.add_marker(pytest.mark.xdist_group(item.nodeid.split("::", 1)[0]))
    elif shared := _shared_flight(item):
        item.add_marker(pytest.mark.xdist_group(shared))


def pytest_collection_modifyitems(config, items):
    # the longest units first, the fine-grained last to even out the end: real time (one group), then
    # the integration tests sharing a flight (a group each: the lockstep hover's is ~90 s of CPU, one
    # worker's, and would make the run's tail if it came last), the unit modules (a group each), then
    # the other integration tests (each on its own)
    items.sort(key=_order)


def _order(item) -> int:
    if item.get_closest_marker(REALTIME):
        return 0
    if item.nodeid.startswith("tests/unit/"):
        return 2
    return 1 if _shared_flight(item) else 3


def _shared_flight(item) -> str | None:
    """The first module- or session-scoped fixture of the project's that `item` uses (a flight
    several tests read): its tests stay on one worker, so it is flown once."""
    info = getattr(item, "_fixtureinfo", None)
    for name, defs in info.name2fixturedefs.items() if info else ():
        if defs[-1].scope in ("module", "session") and defs[-1].baseid.startswith("tests"):
            return f"{defs[-1].baseid}::{name}"
    return None


def _schedule_worker(policy: int) -> bool:
    """Every thread of this worker at `policy` (the processes it starts inherit it); False where
    the OS refuses (leaving SCHED_IDLE needs privilege)."""
    if os.sched_getscheduler(0) == policy:
        return True
    try:
        for tid in os.listdir("/proc/self/task"):
            try:
                os.sched_setscheduler(int(tid), policy, os.sched_param(0))
            except ProcessLookupError:   # a thread that ended meanwhile
                pass
    except PermissionError:
        return False
    return True


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item):
    if not UNDER_XDIST:   # one process: nothing runs beside a test
        return
    if item.get_closest_marker(REALTIME):
        if not _schedule_worker(os.SCHED_OTHER):
            warnings.warn("a real-time test runs at SCHED_IDLE: the OS refused normal scheduling back")
    else:
        _schedule_worker(os.SCHED_IDLE)
