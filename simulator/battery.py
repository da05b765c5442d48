"""Flight battery: charge counting, open-circuit voltage and sag under load (pure).

Current is modelled from the motors' thrust (about linear over a small
frame's working range): I = idle_a + current_a_per_n * sum(thrust); the
terminal voltage is the open-circuit voltage of the state of charge
(a LiPo curve per cell) minus I * internal resistance.
"""
from __future__ import annotations

import numpy as np

# LiPo open-circuit voltage per cell against state of charge
_SOC = np.array([0.0, 0.05, 0.1, 0.2, 0.5, 0.8, 0.9, 1.0])
_OCV_V = np.array([3.3, 3.55, 3.65, 3.72, 3.8, 3.95, 4.05, 4.2])


class Battery:
    @classmethod
    def of(cls, vehicle) -> Battery:
        """A full pack of this airframe (its vehicle file's battery_* numbers)."""
        return cls(vehicle.battery_capacity_mah, vehicle.battery_cells, vehicle.battery_internal_resistance_ohm,
                   vehicle.battery_current_a_per_n, vehicle.battery_idle_current_a)

    def __init__(self, capacity_mah: float, cells: int, internal_resistance_ohm: float,
                 current_a_per_n: float, idle_current_a: float):
        self.capacity_mah = capacity_mah
        self.cells = cells
        self.r_ohm = internal_resistance_ohm
        self.a_per_n = current_a_per_n
        self.idle_a = idle_current_a
        self.consumed_mah = 0.0
        self.current_a = idle_current_a

    @property
    def remaining(self) -> float:
        return float(min(1.0, max(0.0, 1.0 - self.consumed_mah / self.capacity_mah)))

    @property
    def voltage_v(self) -> float:
        ocv = self.cells * float(np.interp(self.remaining, _SOC, _OCV_V))
        return max(0.0, ocv - self.current_a * self.r_ohm)

    def step(self, dt_s: float, motor_thrust_n) -> None:
        """Draw the current of this thrust for dt_s."""
        self.current_a = self.idle_a + self.a_per_n * float(sum(motor_thrust_n))  # 4 floats: no numpy call
        self.consumed_mah += self.current_a * dt_s / 3.6  # A s -> mAh

    def fields(self) -> dict:
        return {"voltage_v": self.voltage_v, "current_a": self.current_a,
                "consumed_mah": self.consumed_mah, "remaining": self.remaining, "cells": self.cells}
