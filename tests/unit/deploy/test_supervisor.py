"""The launcher's supervisor (deploy/supervisor.py): detection and restart policy, on fake
processes and a fake clock, and a real stopped process."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import deploy.supervisor
from deploy.supervisor import (BEAT_SILENCE_S, HEALTH_SILENCE_S, POLL_S, PRIORITY_ENV, RECONNECT_GRACE_S, REMOTE_BEAT_SILENCE_S,
                               START_S,
                               Supervisor, backoff_s, loop_runnable_ns, process_state, supervisor_priority)
from services.stack import StackError, load_stack


class FakeProc:
    def __init__(self, pid=1, status=None):
        self.pid, self.returncode = pid, status

    def poll(self):
        return self.returncode


class FakeLauncher:
    def __init__(self, tmp_path, policies):
        spec = type("Spec", (), {})
        self.specs = {}
        for name, (policy, limit) in policies.items():
            s = spec()
            s.restart, s.restart_limit, s.hang_restart_s = policy, limit, 1.0
            self.specs[name] = s
        self.stack = type("Stack", (), {"service": lambda _, n: self.specs[n]})()
        self.run_dir = tmp_path
        self.procs = {n: FakeProc(pid=10 ** 9 + i) for i, n in enumerate(policies)}   # no such pids
        self.restarted = []

        self.killed = []

    def restart(self, name):
        self.restarted.append(name)
        self.procs[name] = FakeProc(pid=10 ** 9 + 100 + len(self.restarted))

    def kill(self, name):
        self.killed.append(name)
        self.procs[name].returncode = -9


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def supervisor(tmp_path, policies, real_time=True):
    launcher, clock, said = FakeLauncher(tmp_path, policies), Clock(), []
    return Supervisor(launcher, list(policies), real_time, say=said.append, clock=clock), launcher, clock, said


def test_a_dead_service_is_restarted_after_a_growing_back_off_until_its_limit(tmp_path):
    sup, launcher, clock, said = supervisor(tmp_path, {"attitude": ("on-failure", 2)})
    for restart in range(2):
        launcher.procs["attitude"].returncode = -9
        assert sup.poll() == [] and sup.watches["attitude"].state == "restarting"
        clock.t += backoff_s(restart) - 0.01
        sup.poll()
        assert len(launcher.restarted) == restart, "restarted before its back-off"
        clock.t += 0.02
        sup.poll()
        assert len(launcher.restarted) == restart + 1
    launcher.procs["attitude"].returncode = 1
    assert sup.poll() == ["attitude"], "a third death past the limit is lost"
    assert sup.poll() == [], "reported once"
    w = sup.watches["attitude"]
    assert (w.exits, w.restarts, w.state, w.last_status) == (3, 2, "exited", 1)
    assert "killed by signal 9" in said[0] and "restart limit 2 reached" in said[-1]
    saved = json.loads((tmp_path / "supervisor.json").read_text())
    assert saved["services"]["attitude"]["restarts"] == 2
    assert len([e for e in saved["events"] if e["service"] == "attitude"]) == 5   # (and the clock's jumps: stalls)
    health = sup.health_message()   # (the clock's jumps past a poll are the supervisor's stalls: counted apart)
    assert health["state"] == "degraded" and {k: v for k, v in health["rejected"].items() if "supervisor" not in k} == {
        "exited_attitude": 3, "restarted_attitude": 2}


def test_back_off_first_short_then_doubling_to_a_bound():
    assert [backoff_s(n) for n in range(7)] == [0.0, 0.5, 1.0, 2.0, 4.0, 8.0, 8.0]


def test_policies_never_always_and_lockstep(tmp_path):
    sup, launcher, clock, said = supervisor(tmp_path, {"recorder": ("never", 3), "planner": ("always", 3),
                                                       "position": ("on-failure", 3)})
    launcher.procs["recorder"].returncode = -9
    launcher.procs["planner"].returncode = 0      # "always": a clean exit is restarted too
    launcher.procs["position"].returncode = 0     # "on-failure": a clean exit is not a failure
    assert sup.poll() == ["recorder"]
    assert sup.watches["planner"].state == "restarting" and sup.watches["position"].state == "gave-up"
    assert any("policy never" in s for s in said)
    lock, launcher, _, said = supervisor(tmp_path, {"attitude": ("on-failure", 3)}, real_time=False)
    launcher.procs["attitude"].returncode = -9
    assert lock.poll() == ["attitude"] and launcher.restarted == []
    assert "lockstep" in said[-1]


def test_silence_is_reported_in_real_time_only_and_ends_with_the_next_health(tmp_path):
    sup, launcher, clock, said = supervisor(tmp_path, {"position": ("on-failure", 3)})
    sup.health_seen("position")
    clock.t += HEALTH_SILENCE_S + 0.1
    sup.poll()
    assert sup.watches["position"].state == "silent" and "no health message" in said[-1]
    sup.health_seen("position")
    sup.poll()
    assert sup.watches["position"].state == "running" and sup.watches["position"].silences == 1
    lock, _, clock, _ = supervisor(tmp_path, {"position": ("on-failure", 3)}, real_time=False)
    clock.t += 10 * HEALTH_SILENCE_S
    lock.poll()
    assert lock.watches["position"].state == "running"


def test_a_stopped_process_is_seen_at_once_and_again_when_it_runs(tmp_path):
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        sup, launcher, clock, said = supervisor(tmp_path, {"vision": ("on-failure", 3)})
        launcher.procs["vision"] = proc
        proc.send_signal(signal.SIGSTOP)
        for _ in range(500):   # the signal takes effect when the process next runs: on a loaded machine
            if process_state(proc.pid) == "T":   # (the suite's idle priority) that can take a while
                break
            time.sleep(0.01)
        sup.poll()
        assert sup.watches["vision"].state == "stopped", process_state(proc.pid)
        proc.send_signal(signal.SIGCONT)
        sup.poll()
        assert sup.watches["vision"].state == "running" and sup.watches["vision"].stops == 1
    finally:
        proc.kill()
        proc.wait()


def test_stack_restart_keys_are_checked(tmp_path):
    base = (Path(__file__).resolve().parents[3] / "deploy" / "stacks" / "default.toml").read_text()
    stack = load_stack(None)
    assert stack.service("attitude").restart == "on-failure" and stack.service("recorder").restart == "never"
    assert stack.service("sim").restart == "never" and stack.service("attitude").restart_limit == 3
    for extra, message in (('restart = "sometimes"', "must be one of"), ("restart_limit = -1", "within 0..100"),
                           ('restart = "always"', "never restarted")):
        section = "[services.sim]" if "always" in extra else "[services.attitude]"
        path = tmp_path / "s.toml"
        path.write_text(base.replace(section, f"{section}\n{extra}", 1))
        with pytest.raises(StackError, match=message):
            load_stack(str(path))


def run_for(sup, clock, seconds, beating=(), step=0.1):
    """Poll every `step` for `seconds`, the services in `beating` beating before each poll."""
    for _ in range(round(seconds / step)):
        clock.t += step
        for name in beating:
            sup.beat_seen(name)
        sup.poll()


def test_a_stuck_loop_is_a_hang_killed_and_restarted_after_its_bound(tmp_path):
    sup, launcher, clock, said = supervisor(tmp_path, {"attitude": ("on-failure", 3)})
    run_for(sup, clock, 1.0, beating=["attitude"])
    run_for(sup, clock, BEAT_SILENCE_S + 0.1)   # its loop stuck: no beat
    w = sup.watches["attitude"]
    assert w.state == "stuck" and w.stucks == 1 and "its loop sent no beat for 0.4" in said[-1], said
    assert launcher.killed == []
    run_for(sup, clock, 1.1)
    assert launcher.killed == ["attitude"] and w.hangs == 1 and w.state == "restarting", said
    assert "hung (stuck for 1." in said[-1]
    sup.beat_seen("attitude")   # a beat of the killed process still on its way: not the new one's
    run_for(sup, clock, backoff_s(0) + 0.1)
    assert launcher.restarted == ["attitude"] and w.state == "running" and w.exits == 0
    run_for(sup, clock, HEALTH_SILENCE_S + 1.0)   # starting slowly: no beat, no health
    assert w.state == "silent" and launcher.killed == ["attitude"], "a slow start-up is not a hang"
    run_for(sup, clock, 1.0, beating=["attitude"])
    assert w.state == "running" and sup.health_message()["rejected"] == {
        "stuck_attitude": 1, "silent_attitude": 1, "hung_attitude": 1, "restarted_attitude": 1}


def test_a_loop_that_beats_again_before_its_bound_is_left_alone(tmp_path):
    sup, launcher, clock, said = supervisor(tmp_path, {"motors": ("on-failure", 3)})
    run_for(sup, clock, 0.5, beating=["motors"])
    run_for(sup, clock, 0.6)
    assert sup.watches["motors"].state == "stuck"
    run_for(sup, clock, 2.0, beating=["motors"])
    assert sup.watches["motors"].state == "running" and launcher.killed == [] and "beats again" in said[-1]


def test_a_stopped_service_past_its_bound_is_killed_unless_its_policy_says_never(tmp_path, monkeypatch):
    stopped = set()
    monkeypatch.setattr(deploy.supervisor, "process_state", lambda pid: "T" if pid in stopped else "S")
    sup, launcher, clock, said = supervisor(tmp_path, {"position": ("on-failure", 3), "recorder": ("never", 3)})
    stopped |= {launcher.procs["position"].pid, launcher.procs["recorder"].pid}
    run_for(sup, clock, 0.1)
    assert sup.watches["position"].state == "stopped" and sup.watches["recorder"].state == "stopped"
    run_for(sup, clock, 1.1)
    assert launcher.killed == ["position"] and sup.watches["recorder"].state == "stopped"
    run_for(sup, clock, backoff_s(0) + 0.1)
    assert launcher.restarted == ["position"]
    lock, launcher, clock, _ = supervisor(tmp_path, {"position": ("on-failure", 3)}, real_time=False)
    stopped.add(launcher.procs["position"].pid)
    run_for(lock, clock, 5.0)
    assert launcher.killed == [] and lock.watches["position"].state == "stopped", "lockstep: reported only"


def test_stack_hang_bound_is_checked(tmp_path):
    base = (Path(__file__).resolve().parents[3] / "deploy" / "stacks" / "default.toml").read_text()
    assert load_stack(None).service("attitude").hang_restart_s == 0.5
    for value in ("0.0", "nan", '"1"', "61"):
        path = tmp_path / "s.toml"
        path.write_text(base.replace("[services.attitude]", f"[services.attitude]\nhang_restart_s = {value}", 1))
        with pytest.raises(StackError, match="hang_restart_s"):
            load_stack(str(path))


def test_a_start_up_silent_past_its_bound_is_a_hang(tmp_path):
    sup, launcher, clock, said = supervisor(tmp_path, {"planner": ("on-failure", 3)})
    run_for(sup, clock, HEALTH_SILENCE_S + START_S - 0.5)
    assert sup.watches["planner"].state == "silent" and launcher.killed == []
    run_for(sup, clock, 1.0)
    assert launcher.killed == ["planner"] and any("hung (silent for 30." in line for line in said), said


def test_a_record_that_cannot_be_written_is_said_once_and_supervision_goes_on(tmp_path):
    sup, launcher, clock, said = supervisor(tmp_path, {"attitude": ("on-failure", 3)})
    sup.path = tmp_path / "gone" / "supervisor.json"   # its folder removed under it
    launcher.procs["attitude"].returncode = -9
    sup.poll()
    run_for(sup, clock, 1.0)
    assert launcher.restarted == ["attitude"]
    assert sum("cannot write" in line for line in said) == 1, said


def test_another_machines_service_is_reported_by_its_beats_never_acted_on(tmp_path):
    launcher, clock, said = FakeLauncher(tmp_path, {"planner": ("on-failure", 3)}), Clock(), []
    sup = Supervisor(launcher, ["planner"], True, say=said.append, clock=clock, remote=["attitude", "planner"])
    assert list(sup.remote) == ["attitude"]   # a service of this machine is watched as its own
    run_for(sup, clock, 2.0, beating=["planner"])
    assert sup.remote["attitude"].state == "unseen" and said == []   # not beating yet: not judged
    run_for(sup, clock, 1.0, beating=["planner", "attitude"])
    run_for(sup, clock, REMOTE_BEAT_SILENCE_S - 0.15, beating=["planner"])
    assert sup.remote["attitude"].state == "running"
    run_for(sup, clock, 0.3, beating=["planner"])   # its beats stopped coming across the link
    assert sup.remote["attitude"].state == "stuck" and "attitude no beat from its host for 0.6" in said[-1], said
    assert launcher.killed == [] and launcher.restarted == []   # its own host's supervisor acts
    assert sup.health_message()["rejected"] == {"stuck_remote_attitude": 1}
    assert "attitude stuck (remote)" in sup.health_message()["detail"]
    run_for(sup, clock, 0.5, beating=["planner", "attitude"])
    assert sup.remote["attitude"].state == "running" and "beats again" in said[-1]
    assert json.loads((tmp_path / "supervisor.json").read_text())["remote"]["attitude"]["stucks"] == 1
    lockstep = Supervisor(launcher, ["planner"], False, say=said.append, clock=clock, remote=["attitude"])
    assert lockstep.remote == {}   # no beats in lockstep


LOOPS = {"motors": ("on-failure", 3), "attitude": ("on-failure", 3), "position": ("on-failure", 3)}


def flying(tmp_path):
    """Three loops beating, the motor driver with its 0.2 s hang bound (the default stack's)."""
    sup, launcher, clock, said = supervisor(tmp_path, LOOPS)
    sup.watches["motors"].hang_s = 0.2
    run_for(sup, clock, 1.0, beating=list(LOOPS))
    return sup, launcher, clock, said


def test_a_supervisor_that_woke_late_kills_no_healthy_loop(tmp_path):
    # the whole launcher starved 0.6 s (no poll, no beat received), then the beats' backlog
    # arrives one loop at a time: every loop looked silent 0.7 s, past 0.3 s + the driver's 0.2 s
    sup, launcher, clock, said = flying(tmp_path)
    clock.t += 0.6
    sup.poll()
    for _ in range(5):
        clock.t += POLL_S
        sup.beat_seen("attitude")   # the motor driver's beats still on their way at the first poll
        sup.poll()
        sup.beat_seen("motors")
        sup.beat_seen("position")
    assert launcher.killed == [] and all(w.state == "running" and w.stucks == 0 for w in sup.watches.values()), said
    assert sup.own["late"] == 1 and sup.own["late_max_s"] == pytest.approx(0.5)
    assert "woke 0.50 s late: its own stall" in said[-1] and sup.health_message()["rejected"] == {"supervisor_late": 1}


def test_a_supervisor_that_hears_no_beat_from_any_loop_kills_none(tmp_path):
    # the polls on time, but no beat delivered for 0.6 s (its Zenoh thread starved): all at once
    sup, launcher, clock, said = flying(tmp_path)
    run_for(sup, clock, 0.6)
    assert launcher.killed == [] and all(w.state == "running" for w in sup.watches.values()), said
    run_for(sup, clock, 1.0, beating=list(LOOPS))
    assert launcher.killed == [] and all(w.stucks == 0 for w in sup.watches.values()), said
    assert sup.own["deaf"] == 1 and 0.6 <= sup.own["deaf_max_s"] <= 0.7 and "heard no beat from any loop" in said[-1]


def test_loops_reconnecting_one_by_one_after_their_router_came_back_are_not_killed(tmp_path):
    # a ground station's router re-opened by its link check (bench/two_hosts.py --link bad --outage
    # 6:25): no beat from anyone for 8 s, then the sessions reconnect one by one, Zenoh retrying
    # every 1 s up to 4 s: the planner and the bridge, heard 0.8 s after the first, were killed
    sup, launcher, clock, said = flying(tmp_path)
    run_for(sup, clock, 8.0)
    run_for(sup, clock, 1.0, beating=["attitude"])
    run_for(sup, clock, 2.5, beating=["attitude", "position"])
    assert launcher.killed == [] and sup.watches["motors"].stucks == 0, said
    run_for(sup, clock, 2.0, beating=list(LOOPS))
    assert launcher.killed == [] and all(w.state == "running" for w in sup.watches.values()), said
    # a loop that never comes back is still killed, once the grace has passed
    sup, launcher, clock, said = flying(tmp_path)
    run_for(sup, clock, 8.0)
    run_for(sup, clock, RECONNECT_GRACE_S + 1.0, beating=["attitude", "position"])
    assert launcher.killed == ["motors"], said
    # a short deaf spell (a starved receiving thread) gives no grace
    sup, launcher, clock, said = flying(tmp_path)
    run_for(sup, clock, 0.5)
    run_for(sup, clock, 0.8, beating=["attitude", "position"])
    assert launcher.killed == ["motors"], said


def test_a_real_hang_is_still_seen_within_half_a_second_and_killed(tmp_path):
    sup, launcher, clock, said = flying(tmp_path)
    hung = clock.t   # its last beat
    for _ in range(10):   # the others beat on
        run_for(sup, clock, POLL_S, beating=["attitude", "position"])
        if sup.watches["motors"].state == "stuck":
            break
    assert sup.watches["motors"].state == "stuck" and clock.t - hung <= 0.5, said
    run_for(sup, clock, 0.3, beating=["attitude", "position"])
    assert launcher.killed == ["motors"] and clock.t - hung <= 0.8 and "hung (stuck for 0." in said[-1], said
    # a stall of the supervisor during a hang: the hang is seen later by the stall only
    sup, launcher, clock, said = flying(tmp_path)
    hung = clock.t
    run_for(sup, clock, 0.1, beating=["attitude", "position"])
    clock.t += 0.4   # starved: a poll 0.3 s late
    sup.beat_seen("attitude")
    sup.beat_seen("position")
    sup.poll()
    assert sup.watches["motors"].state == "running"   # 0.5 s of silence, 0.3 s of it the supervisor's
    run_for(sup, clock, 0.2, beating=["attitude", "position"])
    assert sup.watches["motors"].state == "stuck" and clock.t - hung <= 0.5 + 0.3 + 1e-9, said
    # one loop alone has no other to vouch for the supervisor's hearing: its silence counts
    sup, launcher, clock, said = supervisor(tmp_path, {"motors": ("on-failure", 3)})
    run_for(sup, clock, 1.0, beating=["motors"])
    run_for(sup, clock, 0.4)
    assert sup.watches["motors"].state == "stuck" and sup.own["deaf"] == 0


class LoopThreads:
    """The loops' threads' running-or-waiting time as /proc would show it: growing at each read
    for those `running`."""

    def __init__(self, sup, running):
        self.sup, self.running, self.ran = sup, set(running), {}
        sup.loop_runnable = self

    def __call__(self, pid):
        name = next(n for n, p in self.sup.launcher.procs.items() if p.pid == pid)
        self.ran[name] = self.ran.get(name, 0) + (50_000 if name in self.running else 0)
        return self.ran[name]


def test_loops_that_all_hang_at_once_are_killed_though_no_beat_arrives_from_anyone(tmp_path):
    # every loop blocked at once (e.g. on one hung disk): no beat from anyone looks like a deaf
    # supervisor, but /proc shows the loops' threads have neither run nor waited to since
    sup, launcher, clock, said = flying(tmp_path)
    threads = LoopThreads(sup, running=LOOPS)
    run_for(sup, clock, 0.5, beating=list(LOOPS))
    hung = clock.t
    threads.running = set()
    run_for(sup, clock, 0.4)
    assert all(w.state == "stuck" and w.idle for w in sup.watches.values()), said
    assert "and its thread has been blocked for 0.40 s" in said[-1], said   # seen within 0.5 s
    run_for(sup, clock, 1.1)   # the motor driver's bound 0.2 s, the others' 1.0 s
    assert sorted(launcher.killed) == sorted(LOOPS) and clock.t - hung <= 1.5 + 1e-9, said


def test_a_deaf_supervisor_still_kills_no_loop_whose_thread_runs(tmp_path):
    # no beat delivered for 0.6 s, every loop's thread running: its own deafness, as before
    sup, launcher, clock, said = flying(tmp_path)
    threads = LoopThreads(sup, running=LOOPS)
    run_for(sup, clock, 0.6)
    assert launcher.killed == [] and all(w.state == "running" for w in sup.watches.values()), said
    # ... but one of them whose thread is blocked is stuck, the others spared
    threads.running = {"attitude", "position"}
    run_for(sup, clock, 0.6)
    assert launcher.killed == ["motors"] and sup.watches["attitude"].state == "running", said


def test_a_loops_running_and_waiting_time_is_read_from_proc():
    blocked = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        time.sleep(0.5)   # imports done: the sleeper blocks from here
        first = {p: loop_runnable_ns(p.pid) for p in (blocked, busy)}
        time.sleep(0.3)
        assert loop_runnable_ns(blocked.pid) == first[blocked]
        assert loop_runnable_ns(busy.pid) > first[busy]
    finally:
        for p in (blocked, busy):
            p.kill()
            p.wait()
    assert loop_runnable_ns(blocked.pid) is None   # gone


def test_the_watch_thread_polls_on_its_own_and_says_what_ended_it(tmp_path):
    launcher, said = FakeLauncher(tmp_path, {"attitude": ("never", 3)}), []
    sup = Supervisor(launcher, ["attitude"], True, say=said.append)
    sup.start(priority=0)
    try:
        launcher.procs["attitude"].returncode = -9
        deadline = time.monotonic() + 10.0
        lost = []
        while not lost and time.monotonic() < deadline:
            lost = sup.take_lost()
            time.sleep(0.01)
        assert lost == ["attitude"] and sup.take_lost() == [] and sup.scheduling == "normal"
        sup.clock = lambda: 1 / 0   # the next poll fails: the caller must hear of it
        while sup._failure is None and time.monotonic() < deadline:
            time.sleep(0.01)
        with pytest.raises(RuntimeError, match="watch failed"):
            sup.take_lost()
    finally:
        sup.stop()


def test_the_supervisor_runs_below_every_loop_it_watches(monkeypatch):
    stack = load_stack(None)
    monkeypatch.delenv(PRIORITY_ENV, raising=False)
    assert supervisor_priority(stack, ["motors", "motors.b", "attitude", "recorder"]) == stack.service("recorder").priority - 1
    assert supervisor_priority(stack, ["motors", "attitude"]) == stack.service("attitude").priority - 1
    assert supervisor_priority(stack, ["mavlink"]) == 0   # no loop at a real-time priority: neither is it
    monkeypatch.setenv(PRIORITY_ENV, "0")
    assert supervisor_priority(stack, ["motors"]) == 0
    for bad in ("x", "100", "-1"):
        monkeypatch.setenv(PRIORITY_ENV, bad)
        with pytest.raises(ValueError, match=PRIORITY_ENV):
            supervisor_priority(stack, ["motors"])


def test_its_real_time_scheduling_holds_or_is_reported_and_its_children_start_normal():
    code = ("import json, os, threading, time; from deploy.supervisor import apply_watch_scheduling\n"
            "threading.Thread(target=time.sleep, args=(5,), daemon=True).start()  # another thread: Zenoh's\n"

            "def watch():\n"
            "    global said, child; said = apply_watch_scheduling(1)\n"
            "    pid = os.fork()  # a restart's process, started from the watch\n"
            "    if pid == 0: os._exit(os.sched_getscheduler(0))\n"
            "    child = os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1])\n"
            "t = threading.Thread(target=watch); t.start(); t.join()\n"
            "threads = {int(t): os.sched_getscheduler(int(t)) & 0xff for t in os.listdir('/proc/self/task')}\n"
            "print(json.dumps({'said': said, 'main': threads.pop(os.getpid()), 'others': sorted(threads.values()),\n"
            "                  'child': child}))\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                          cwd=Path(__file__).resolve().parents[3])
    assert done.returncode == 0, done.stderr
    got = json.loads(done.stdout)
    assert got["main"] == os.sched_getscheduler(0)   # the caller's screen and analysis: as they were
    if got["said"] == "fifo 1":   # permitted: the watch and the other thread real time; a child not
        assert got["others"] == [os.SCHED_FIFO] and got["child"] == os.SCHED_OTHER, got
    else:
        assert got["said"].startswith("priority 1 refused") and got["said"].endswith("normal scheduling"), got


FREEZER = Path("/sys/fs/cgroup/freezer")


@pytest.mark.skipif(not os.access(FREEZER, os.W_OK), reason="needs cgroup v1's freezer, writable (root)")
def test_the_launcher_kills_a_process_blocked_in_the_kernel_without_waiting_for_it(tmp_path):
    """A process frozen by the cgroup freezer (as one blocked on a hung disk) dies of SIGKILL only
    when it wakes: the supervisor's kill must return at once, and the process be reaped later."""
    from deploy.launcher import Launcher
    launcher = Launcher(load_stack(None), tmp_path / "run", "tcp/127.0.0.1:7447")
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    launcher.procs["attitude"] = proc
    group = FREEZER / f"zenpilot-test-{os.getpid()}"
    group.mkdir()
    try:
        (group / "cgroup.procs").write_text(str(proc.pid))
        (group / "freezer.state").write_text("FROZEN")
        for _ in range(200):
            if (group / "freezer.state").read_text().strip() == "FROZEN":
                break
            time.sleep(0.01)
        t0 = time.monotonic()
        launcher.kill("attitude")
        assert time.monotonic() - t0 < 0.2 and proc.poll() is None and launcher.dying == [proc]
        time.sleep(0.2)
        assert proc.poll() is None   # frozen: the kill waits for it to wake
        (group / "freezer.state").write_text("THAWED")
        launcher._reap_dying(5.0)
        assert proc.returncode == -signal.SIGKILL and launcher.dying == []
    finally:
        (group / "freezer.state").write_text("THAWED")
        proc.kill()
        proc.wait()
        group.rmdir()
