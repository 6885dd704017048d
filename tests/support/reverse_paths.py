"""Reversing paths as people write them: a three-point turn as a CSV whose negative `v` marks the
points reached backwards, and a parallel park as a YAML `points:` list whose reversing leg
meets the forward one in line (a cusp with no turn in place)."""

from __future__ import annotations

THREE_POINT = """x,y,v
0,0,0.3
0.6,0,0.3
0.3,0.3,-0.25
0.9,0.45,0.3
"""


def parallel_park_points() -> dict:
    """Forward 1 m along x, then back into a slot 0.3 m to the right along a smooth S (samples
    every 1 cm), the robot facing +x throughout."""
    fwd = [[0.01 * k, 0.0, 0.3] for k in range(0, 101)]
    back = []
    for k in range(1, 61):
        x = 1.0 - 0.01 * k
        f = (1.0 - x) / 0.6
        back.append([x, -0.3 * (3 * f * f - 2 * f ** 3), -0.2])
    return {"points": fwd + back}
