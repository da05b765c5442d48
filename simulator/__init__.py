"""The plant: rigid-body quadcopter, motors, drag, wind, and sensor models.

Pure Python + numpy; imports flight/ for shared math, never services/.
"""
from simulator.config import SimConfig
from simulator.world import Simulator

__all__ = ["SimConfig", "Simulator"]
