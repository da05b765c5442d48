"""zenpilot message schemas: definitions, key expressions and the strict codec."""

from .core import REASONS, Field, Message, SchemaError
from .messages import (
    ALL, ATTITUDE_COMMAND, ATTITUDE_STATE, BARO, BATTERY, BY_NAME, CAMERA, CLOCK, HEALTH, IMU, MAG,
    MOTOR_PWM, PARAM_SET, PLANNER_COMMAND, PLANNER_MISSION, PLANNER_PLAN, PLANNER_SETPOINT, POSITION_SETPOINT, POSITION_STATE, SIM_TOPICS, SYNC_DONE,
    TRUTH, VISION_POSE, message_for_key,
)

__all__ = [
    "REASONS", "Field", "Message", "SchemaError", "ALL", "BY_NAME", "SIM_TOPICS", "message_for_key",
    "CLOCK", "SYNC_DONE", "IMU", "BARO", "MAG", "CAMERA", "TRUTH", "PLANNER_SETPOINT",
    "VISION_POSE", "POSITION_SETPOINT", "POSITION_STATE", "ATTITUDE_COMMAND", "ATTITUDE_STATE", "MOTOR_PWM", "HEALTH",
    "BATTERY", "PLANNER_COMMAND", "PARAM_SET", "PLANNER_PLAN", "PLANNER_MISSION",
]
