"""How the suite runs on two workers (pytest-xdist, `-n 2 --dist loadgroup` in pyproject.toml).

Tests marked `realtime` fly on the wall clock: they run one at a time, all on one worker, first,
and each has the machine to itself: it takes an exclusive lock that every other test takes
shared, so the other worker waits while a real-time flight runs (under a lockstep flight or a
JAX compile on the other core, a real-time stack's timing is not what the test judges). The
rest runs on both workers, the unit modules first. A unit module stays on one worker (its
module fixtures: an iLQR solver compiled once), and so do the integration tests that read one
module- or session-scoped flight (flown once, not once per worker).
"""

import fcntl
import os
import tempfile

import pytest

REALTIME = "realtime"


def pytest_itemcollected(item):   # as collected: xdist names the groups before other hooks see the items
    if item.get_closest_marker(REALTIME):
        item.add_marker(pytest.mark.xdist_group(REALTIME))
    elif item.nodeid.startswith("tests/unit/"):
        item.add_marker(pytest.mark.xdist_group(item.nodeid.split("::", 1)[0]))
    elif shared := _shared_flight(item):
        item.add_marker(pytest.mark.xdist_group(shared))


def pytest_collection_modifyitems(config, items):
    # the longest units first, the fine-grained last to even out the end: real time (one group), then
    # the unit modules (a group each), then the other integration tests (each on its own)
    items.sort(key=lambda item: (item.get_closest_marker(REALTIME) is None, not item.nodeid.startswith("tests/unit/")))


def _shared_flight(item) -> str | None:
    """The first module- or session-scoped fixture of the project's that `item` uses (a flight
    several tests read): its tests stay on one worker, so it is flown once."""
    info = getattr(item, "_fixtureinfo", None)
    for name, defs in info.name2fixturedefs.items() if info else ():
        if defs[-1].scope in ("module", "session") and defs[-1].baseid.startswith("tests"):
            return f"{defs[-1].baseid}::{name}"
    return None


def _run_lock():
    """The lock file the workers of this run share (None: not under xdist)."""
    run = os.environ.get("PYTEST_XDIST_TESTRUNUID")
    if run is None:
        return None
    return open(os.path.join(tempfile.gettempdir(), f"zenpilot-tests-{run}.lock"), "a")


_LOCK = _run_lock()


@pytest.hookimpl(hookwrapper=True)   # setup, call and teardown: a real-time test alone on the machine
def pytest_runtest_protocol(item, nextitem):
    if _LOCK is None:
        yield
        return
    fcntl.flock(_LOCK, fcntl.LOCK_EX if item.get_closest_marker(REALTIME) else fcntl.LOCK_SH)
    try:
        yield
    finally:
        fcntl.flock(_LOCK, fcntl.LOCK_UN)
