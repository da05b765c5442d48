"""Pure flight algorithms (no middleware): quaternions, vehicle model, mixer,
control laws of document 000, camera model.

Frames: world ENU (z up), body FLU (x forward, y left, z up); quaternions are
[w, x, y, z] body->world; Euler angles ZYX, R = Rz(yaw) Ry(pitch) Rx(roll).
"""
