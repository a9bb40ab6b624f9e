"""An EGM sensor we did not write, against rigbridge's EGM twin: abb-robot-client's `EGM`
class (PyPI `abb-robot-client`) reads the robot's state and commands a joint motion.

Prints the UDP port it listens on as its first line, then one JSON line: what it saw first,
whether motors and RAPID were on, and the feedback after the motion. Driven by tests/egm.rs.
"""
import json
import math

import numpy as np
from abb_robot_client.egm import EGM

PERIOD_S = 0.004
# Joint 1 moves this far on a cosine profile: 7.9 deg/s and 12.3 deg/s^2 at most, well
# inside the IRB 120's limits.
DISTANCE_DEG = 10.0
DURATION_S = 2.0

egm = EGM(port=0)
print(egm.socket.getsockname()[1], flush=True)


def receive(timeout=2.0):
    ok, state = egm.receive_from_robot(timeout)
    if not ok:
        raise SystemExit(f"no EgmRobot within {timeout} s")
    return state


first = receive(10.0)
start = np.array(first.joint_angles, dtype=float)
report = {
    "first": start.tolist(),
    "motors_on": bool(first.motors_on),
    "rapid_running": bool(first.rapid_running),
    "axes": len(start),
}
still = np.zeros(len(start))
egm.send_to_robot(start, still)
for _ in range(50):
    receive()
    egm.send_to_robot(start, still)
cycles = int(DURATION_S / PERIOD_S)
command = start.copy()
for i in range(cycles + 1):
    receive()
    x = i / cycles
    command = start.copy()
    command[0] += DISTANCE_DEG * (1.0 - math.cos(math.pi * x)) / 2.0
    speed = still.copy()
    speed[0] = DISTANCE_DEG * math.pi / (2.0 * DURATION_S) * math.sin(math.pi * x)
    egm.send_to_robot(command, speed)
for _ in range(250):
    receive()
    egm.send_to_robot(command, still)
last = receive()
report["final"] = last.joint_angles.tolist()
report["planned"] = last.joint_angles_planned.tolist()
report["commanded"] = command.tolist()
print(json.dumps(report), flush=True)
egm.close()
