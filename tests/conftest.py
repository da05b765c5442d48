"""How the suite runs on two workers (pytest-xdist, `-n 2 --dist loadgroup` in pyproject.toml).

Tests marked `realtime` fly on the wall clock: they run one at a time, all on one worker, first
(they are the long pole), while the other worker takes everything else, the unit modules first. Everything not real
time runs at a lower CPU priority (nice 10, where the OS lets a worker take it back), so a
lockstep flight or a JAX compile on the other core never starves a real-time stack's
unprioritised processes (recorder, router, the test's own client). A unit module stays on one
worker (its module fixtures: an iLQR solver compiled once), and so do the integration tests
that read one module- or session-scoped flight (flown once, not once per worker).
"""

import os

import pytest

REALTIME = "realtime"
NICE_NOT_REALTIME = 10
# a worker can lower its niceness again only with the privilege to (root, CAP_SYS_NICE)
_CAN_RENICE = os.environ.get("PYTEST_XDIST_WORKER") is not None and os.geteuid() == 0


@pytest.hookimpl(tryfirst=True)   # before xdist names the groups
def pytest_collection_modifyitems(config, items):
    # the longest units first, the fine-grained last to even out the end: real time (one group), then
    # the unit modules (a group each), then the other integration tests (each on its own)
    items.sort(key=lambda item: (item.get_closest_marker(REALTIME) is None, not item.nodeid.startswith("tests/unit/")))
    for item in items:
        if item.get_closest_marker(REALTIME):
            item.add_marker(pytest.mark.xdist_group(REALTIME))
        elif item.nodeid.startswith("tests/unit/"):
            item.add_marker(pytest.mark.xdist_group(item.nodeid.split("::", 1)[0]))
        elif shared := _shared_flight(item):
            item.add_marker(pytest.mark.xdist_group(shared))


def _shared_flight(item) -> str | None:
    """The first module- or session-scoped fixture of the project's that `item` uses (a flight
    several tests read): its tests stay on one worker, so it is flown once."""
    for name, defs in getattr(item, "_fixtureinfo", None) and item._fixtureinfo.name2fixturedefs.items() or ():
        if defs[-1].scope in ("module", "session") and defs[-1].baseid.startswith("tests"):
            return f"{defs[-1].baseid}::{name}"
    return None


@pytest.hookimpl(tryfirst=True)   # before the item's fixtures start processes, which inherit it
def pytest_runtest_setup(item):
    if _CAN_RENICE:
        os.setpriority(os.PRIO_PROCESS, 0, 0 if item.get_closest_marker(REALTIME) else NICE_NOT_REALTIME)
