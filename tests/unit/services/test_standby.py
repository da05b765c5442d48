"""The hot standby's arbitration (services/standby.py) and the motor driver with it, no I/O."""
import subprocess
import sys
from pathlib import Path

import pytest

import schemas
from deploy.launcher import Launcher
from services.motors import PARAMS, MotorDriver
from services.stack import ServiceSpec, StackError, load_stack, service_of, standby_processes
from services.standby import REJOIN_S, START_GRACE_S, Standby
from tests.unit.services.fake_io import FakeIO
from tests.unit.services.test_motors import HOVER_N, planner

T = 0.025       # takeover bound
TICK = 0.0025   # 400 Hz


def pair(t0=100.0):
    return Standby("motors", active=True, now=t0, takeover_s=T), Standby("motors.b", active=False, now=t0, takeover_s=T)


def run(a: Standby, b: Standby, t0: float, t1: float, a_runs=lambda t: True, b_runs=lambda t: True):
    """Both drivers ticking at 400 Hz from t0 to t1, each hearing what the other sent the tick
    before (one tick of delivery); a_runs/b_runs(t) False: that driver is stopped at t. Returns
    the ticks' senders."""
    sent, t, pending = [], t0, []
    while t < t1:
        for src, ts in pending:
            if a_runs(t):
                a.heard(src, ts, t)
            if b_runs(t):
                b.heard(src, ts, t)
        pending = []
        who = [d.me for d, runs in ((a, a_runs), (b, b_runs)) if runs(t) and d.may_publish(t)]
        pending = [(w, t) for w in who]
        sent.append((t, who))
        t = round(t + TICK, 6)
    return sent


def test_the_standby_is_silent_while_the_active_sends_and_the_active_never_steps_back():
    a, b = pair()
    sent = run(a, b, 100.0, 102.0)
    assert all(who == ["motors"] for _, who in sent)
    assert (a.takeovers, a.stepped_back, b.takeovers, b.stepped_back) == (0, 0, 0, 0)


def test_the_active_killed_the_standby_takes_over_within_the_bound():
    a, b = pair()
    sent = run(a, b, 100.0, 103.0, a_runs=lambda t: t < 102.0)
    gaps = [t for t, who in sent if not who]
    assert gaps and gaps[0] == pytest.approx(102.0) and len(gaps) * TICK <= T + 2 * TICK   # ~25 ms without output
    assert all(who == ["motors.b"] for t, who in sent if t > 102.0 + T + 2 * TICK)
    assert b.active and b.takeovers == 1 and "no output from the other driver" in b.changed


def test_a_driver_resumed_after_a_stop_never_sends_and_stays_standby():
    """SIGSTOP 2 s of the active, then SIGCONT: at its first tick its own output is 2 s old, so it
    steps back before sending, even before it has heard the new active's output."""
    a, b = pair()
    sent = run(a, b, 100.0, 104.0, a_runs=lambda t: not 101.0 <= t < 103.0)
    assert not any(len(who) > 1 for _, who in sent)                    # never two at once
    assert all(who == ["motors.b"] for t, who in sent if t > 101.0 + T + 2 * TICK)
    assert not a.active and a.stepped_back == 1 and "own output" in a.changed and a.takeovers == 0


def test_resumed_before_anyone_heard_it_the_driver_steps_back_on_its_own_clock():
    """Its first tick after the stop, before any delivery (the other's output not yet read)."""
    a = Standby("motors", active=True, now=0.0, takeover_s=T)
    assert a.may_publish(0.0) and a.may_publish(0.0025)
    assert not a.may_publish(2.0) and not a.active
    assert not a.may_publish(2.0 + T / 2)        # it listens a bound first
    a.heard("motors.b", 2.01, 2.02)              # ... and hears the new active: it stays standby
    assert not a.may_publish(2.03) and not a.active


def test_both_silent_the_resumed_driver_takes_over_again_after_its_rejoin_bound():
    a = Standby("motors", active=True, now=0.0, takeover_s=T)
    assert a.may_publish(0.0)
    assert not a.may_publish(1.0)
    assert not a.may_publish(1.0 + REJOIN_S - TICK)     # not yet (it listens REJOIN_S)
    assert a.may_publish(1.0 + REJOIN_S + TICK) and a.active and a.takeovers == 1


def test_a_backlog_still_arriving_is_no_silence():
    """Resumed after a 2 s stop, the stop's backlog of the other's output comes first (old sample
    times), then fresh output after a pause: no takeover while either arrives."""
    a = Standby("motors", active=True, now=0.0, takeover_s=T)
    assert a.may_publish(0.0) and not a.may_publish(2.0)
    t = 2.0
    while t < 2.0 + REJOIN_S + 0.1:   # old messages keep coming in, one a tick
        a.heard("motors.b", 0.3 + (t - 2.0) / 10, t)
        assert not a.may_publish(t), t
        t += TICK
    assert not a.may_publish(t + T - TICK)   # the backlog just ended: a bound of real silence first
    assert a.may_publish(t + T + TICK)      # the other is dead too


def test_two_actives_at_once_resolve_to_the_higher_rank():
    a, b = pair(0.0)
    assert a.may_publish(0.0975)
    b.listen_until = -1.0
    assert b.may_publish(0.1)          # b took over (a's output late in delivery): two actives
    a.heard("motors.b", 0.1, 0.101)    # a, higher rank, keeps going
    assert a.active and a.may_publish(0.1025)
    b.heard("motors", 0.1025, 0.103)   # b hears a's output sent after its takeover: steps back
    assert not b.active and b.stepped_back == 1 and "higher rank" in b.changed
    assert not b.may_publish(0.105)


def test_output_sent_before_the_takeover_does_not_make_the_new_active_step_back():
    b = Standby("motors.b", active=False, now=0.0, takeover_s=T, grace_s=0.0)
    assert b.may_publish(1.0) and b.active
    b.heard("motors", 0.99, 1.001)     # the old active's last output, delivered late
    assert b.active and b.may_publish(1.0025)


def test_a_standby_waits_its_start_grace_and_ignores_its_own_and_unknown_sources():
    b = Standby("motors.b", active=False, now=0.0, takeover_s=T)
    b.heard("motors.b", 0.5, 0.5)
    b.heard("intruder", 0.5, 0.5)
    assert not b.may_publish(START_GRACE_S - 0.01)
    assert b.may_publish(START_GRACE_S + 0.01) and b.changed == "took over: no other driver heard"


def test_an_unknown_instance_is_refused():
    with pytest.raises(ValueError, match="motor driver instance 'motors.c'"):
        Standby("motors.c", active=False, now=0.0, takeover_s=T)


# ---------------------------------------------------------------- the driver with it
class StandbyIO(FakeIO):
    def __init__(self, instance, now, restarted=False):
        super().__init__("motors", PARAMS, {}, rate_hz=400.0, lockstep=False, restarted=restarted)
        self.tick_rate = 400.0
        self.instance, self.t = instance, now
        self.spec = ServiceSpec("motors", "vehicle", 400.0, standby=True)
        self.roles = []

    def now(self):
        return self.t


def _feed(io, t):
    io.received(schemas.PLANNER_SETPOINT, "planner").push(t, planner())
    io.received(schemas.ATTITUDE_COMMAND, "attitude").push(t, {"thrust_n": HOVER_N, "torque_nm": [0.001, 0.0, 0.0],
                                                                "imu_t_s": t})


def test_the_standby_driver_computes_every_tick_sends_nothing_then_takes_over_with_the_same_output():
    io_a, io_b = StandbyIO("motors", 10.0), StandbyIO("motors.b", 10.0)
    a, b = MotorDriver(io_a, on_role=io_a.roles.append), MotorDriver(io_b, on_role=io_b.roles.append)
    assert a.standby.active and not b.standby.active and io_b.problems == ["hot standby: motors.b starts standby"]
    t = 11.0
    for _ in range(20):   # both hear the same inputs; b hears a's output
        _feed(io_a, t)
        _feed(io_b, t)
        a.step(t)
        for _, out in io_a.sent(schemas.MOTOR_PWM)[-1:]:
            io_b.received(schemas.MOTOR_PWM, "motors").push(t, out, source="motors")
        b.step(t)
        t += TICK
    assert len(io_a.sent(schemas.MOTOR_PWM)) == 20 and io_b.sent(schemas.MOTOR_PWM) == []
    last_a = io_a.sent(schemas.MOTOR_PWM)[-1][1]
    for _ in range(12):   # a dies: b keeps computing, and takes over once 25 ms have passed
        _feed(io_b, t)
        b.step(t)
        t += TICK
    sent = io_b.sent(schemas.MOTOR_PWM)
    assert sent and sent[0][0] - (t - 12 * TICK) >= T - TICK
    assert sent[-1][1]["pwm_us"] == pytest.approx(last_a["pwm_us"])   # warm: what a would have sent
    assert io_b.rejected == {"standby_took_over": 1} and io_b.roles == [True] and io_a.roles == [True]


def test_the_takeover_bound_follows_a_param_set():
    io = StandbyIO("motors.b", 10.0)
    d = MotorDriver(io)
    io.set_param("standby_takeover_s", [0.04])
    assert d.standby.takeover_s == 0.04


def test_a_restarted_primary_driver_starts_as_the_standby():
    io = StandbyIO("motors", 10.0, restarted=True)
    d = MotorDriver(io)
    assert not d.standby.active and io.problems == ["hot standby: motors starts standby"]


def test_without_the_option_the_driver_has_no_standby_and_hears_no_peers():
    io = FakeIO("motors", PARAMS, {}, rate_hz=400.0)
    io.tick_rate = 400.0
    d = MotorDriver(io)
    assert d.standby is None and ("motor_pwm", "motors") not in io.inboxes


# ---------------------------------------------------------------- the stack option and the processes
STACK = (Path(__file__).resolve().parents[3] / "deploy" / "stacks" / "default.toml").read_text()


def _stack(tmp_path, text):
    p = tmp_path / "s.toml"
    p.write_text(text)
    return load_stack(p)


def test_the_stack_option_starts_a_second_driver_in_real_time_only(tmp_path):
    stack = _stack(tmp_path, STACK.replace("[services.motors]\n", "[services.motors]\nstandby = true\n"))
    assert stack.service("motors").standby and not stack.service("attitude").standby
    assert standby_processes(stack, list(stack.services), real_time=True) == ["motors.b"]
    assert standby_processes(stack, list(stack.services), real_time=False) == []
    assert standby_processes(load_stack(), list(stack.services), real_time=True) == []
    assert service_of("motors.b") == "motors" and service_of("attitude") == "attitude"
    launcher = Launcher(stack, tmp_path / "run", "tcp/127.0.0.1:7447", params={"motors": ["standby_takeover_s=0.03"]})
    argv = launcher.service_argv("motors.b")
    assert argv[1:3] == ["-m", "services.motors"] and argv[argv.index("--instance") + 1] == "motors.b"
    assert argv[argv.index("--param") + 1] == "standby_takeover_s=0.03"   # the service's overrides
    assert "--instance" not in launcher.service_argv("motors")


@pytest.mark.parametrize("text, needle", [
    ("[services.attitude]\nstandby = true\n", "[services.attitude]: standby: only motors has a hot standby"),
    ("[services.motors]\nstandby = 1\n", "[services.motors] standby: expected bool"),
])
def test_a_bad_standby_option_is_refused_with_where(tmp_path, text, needle):
    head = text.split("\n", 1)[0] + "\n"
    with pytest.raises(StackError) as exc:
        _stack(tmp_path, STACK.replace(head, text, 1))
    assert needle in str(exc.value)


def test_the_standby_driver_refuses_to_run_without_the_option_or_in_lockstep(tmp_path):
    on = tmp_path / "on.toml"
    on.write_text(STACK.replace("[services.motors]\n", "[services.motors]\nstandby = true\n"))
    for extra, needle in ((["--stack", str(load_stack().path)], "has no standby = true"),
                          (["--stack", str(on), "--lockstep"], "the hot standby runs in real time only")):
        r = subprocess.run([sys.executable, "-m", "services.motors", "--instance", "motors.b", *extra,
                            "-e", "tcp/127.0.0.1:9"], check=False, capture_output=True, text=True, timeout=60,
                           cwd=Path(__file__).resolve().parents[3])
        assert r.returncode == 2 and needle in r.stderr and "Traceback" not in r.stderr, r.stderr
