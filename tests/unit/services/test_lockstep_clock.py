"""The one-process clock's CPU split (services/lockstep.py Clock.share_cpu): the simulator's
thread's CPU of a window goes to the inline runs by their wall time, the rest stays the simulator's."""

from types import SimpleNamespace

import pytest

from services import lockstep


def test_the_window_cpu_is_shared_by_wall_time_and_the_total_kept(monkeypatch):
    clock = lockstep.Clock.__new__(lockstep.Clock)
    sim = SimpleNamespace(cpu_inline_s=0.0)
    runs = {p: SimpleNamespace(rt=SimpleNamespace(cpu_inline_s=0.0)) for p in ("attitude", "motors")}
    clock.rt, clock.inline = sim, runs
    clock._window_cpu, clock._window_start = 10.0, 100.0
    clock._window_wall = {"attitude": 0.004, "motors": 0.002}
    # 10 ms of wall, 5 ms of it on the CPU (the thread preempted half the time)
    monkeypatch.setattr(lockstep, "thread_time", lambda: 10.005)
    monkeypatch.setattr(lockstep, "perf_counter", lambda: 100.010)
    clock.share_cpu()
    assert runs["attitude"].rt.cpu_inline_s == pytest.approx(0.002)
    assert runs["motors"].rt.cpu_inline_s == pytest.approx(0.001)
    assert sim.cpu_inline_s == pytest.approx(-0.003)   # the simulator's own: its thread's CPU less these
    assert clock._window_wall == {} and (clock._window_cpu, clock._window_start) == (10.005, 100.010)
    clock.share_cpu()   # an empty window: nothing moves
    assert sim.cpu_inline_s == pytest.approx(-0.003)
