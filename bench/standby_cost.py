"""Per-tick cost of the motor driver's hot standby (services/standby.py, MotorDriver.speaks): what
the 400 Hz loop pays for hearing the other driver's output and deciding whether to send, against
the driver's normal work per tick (bench/failsafe_cost.py's "normal mix" plus the encode of its
motors/pwm). The active driver hears nothing (its subscription leaves out its own messages:
an empty poll); the standby decodes the active's one message per tick.

    python bench/standby_cost.py
"""

import itertools
import timeit

import zenoh

import schemas
from flight.control.mixer import mix_floats
from flight.motor_model import thrust_to_pwm_floats
from flight.vehicle import load_vehicle
from services.runtime import Inbox
from services.standby import Standby

v = load_vehicle("x250")


class _Rt:
    rejected, dropped, lockstep, event_driven, wakes = {}, {}, False, False, False

    def _sync_tick(self, upstream):
        return 0

    def count_dropped(self, key, n=1):
        pass


values = {"pwm_us": [1400.0, 1400.0, 1390.0, 1390.0], "thrust_n": [0.98, 0.98, 0.97, 0.97], "armed": True,
          "saturated": False, "imu_t_s": 0.999}
seq = iter(range(1 << 60))
clock = {"t": 1000.0}


def sample():
    return type("S", (), {"payload": zenoh.ZBytes(schemas.MOTOR_PWM.encode(clock["t"], next(seq), "motors", values))})()


active_box, standby_box = Inbox(_Rt(), schemas.MOTOR_PWM, "p", "motors", 16), Inbox(_Rt(), schemas.MOTOR_PWM, "p", "motors", 16)
active = Standby("motors", active=True, now=clock["t"], takeover_s=0.025)
# the samples' sample times stay put while the clock runs on: a bound it never reaches keeps it the standby
standby = Standby("motors.b", active=False, now=clock["t"] - 2.0, takeover_s=1e9)
samples = [sample() for _ in range(1000)]
counter = itertools.count()


def speaks(box, sb):
    t = sb.last_out + 0.0025 if sb.last_out is not None else clock["t"]   # its own 400 Hz clock
    for m in box.take():
        h = m["header"]
        sb.heard(h["source"], h["t_s"], t)
    return sb.may_publish(t)


def active_tick():
    speaks(active_box, active)


def standby_tick():
    standby_box._on_sample(samples[next(counter) % 1000])   # the Zenoh side's queueing (another thread in flight)
    speaks(standby_box, standby)


def standby_queue_only():
    standby_box._on_sample(samples[next(counter) % 1000])
    standby_box._raw.clear()


pub = schemas.MOTOR_PWM.encode


def normal_tick():
    forces, _ = mix_floats(v, 3.9, [0.001, -0.002, 0.0])
    pwm = thrust_to_pwm_floats(v, forces)
    pub(clock["t"], 1, "motors", {"pwm_us": pwm, "thrust_n": forces, "armed": True, "saturated": False, "imu_t_s": 0.9})


n = 20000
best = {}
for name, fn in (("normal tick (mix, pwm, encode)", normal_tick), ("active: speaks()", active_tick),
                 ("standby: queue one message", standby_queue_only), ("standby: queue + speaks()", standby_tick)):
    best[name] = min(timeit.repeat(fn, number=n, repeat=5)) / n
    print(f"{name:32s} {best[name] * 1e6:7.2f} us per tick (best of 5 x {n})")
assert active.active and not standby.active, "the bench's drivers changed role"
print(f"active's added cost: {best['active: speaks()'] / best['normal tick (mix, pwm, encode)']:.2f}x of a normal tick; "
      f"the standby's speaks(): {(best['standby: queue + speaks()'] - best['standby: queue one message']) * 1e6:.2f} us "
      f"+ {best['standby: queue one message'] * 1e6:.2f} us on Zenoh's side")
