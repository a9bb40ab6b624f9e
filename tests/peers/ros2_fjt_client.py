"""A real ROS 2 Jazzy node (PyPI's ros-jazzy-rclpy on Fast DDS) that moves a rig over DDS,
for tests/ros2_dds.rs: an rclpy ActionClient of control_msgs/action/FollowJointTrajectory
(its Python types built from control_msgs' interface files with the rosidl generators of
the ros-jazzy-* wheels, scripts/test.sh), and a JointTrajectory publisher. It prints
"ready" once the action server (or the topic's subscriber) is found, then one JSON line.

  refusals --rig R
      Four goals that must be refused: a wrong joint name, a NaN, times that do not
      increase, 10^6 points. Reports each one's status, error code and string, and how far
      the arm moved from before the first to after the last.
  motion --rig R --duration-s D
      A goal of D seconds along a straight line in joint space from where the arm is, run
      to its end; then the same line back, canceled at half its duration. Reports for each
      the status, code, feedback rate and longest gap (by arrival), and after the cancel
      where the arm came to rest: its distance from the line and its place along it.
  preempt --rig R --duration-s D
      A goal of D seconds along the line from where the arm is, and at 40 % of it a second
      goal from where the arm then is toward another end (its first point 0.5 s later,
      easing out to rest over 4 s): both results, when each was sent and answered, and
      where the second ended.
  tolerances --rig R
      A 2 s goal along the line whose path tolerance on joint_6 (1 mrad) the twin's servo lag
      cannot keep, then, from where the arm came to rest, a 2 s goal whose goal tolerance
      on joint_1 (0.1 urad) is finer than where a lagging servo ends (and than the wire's
      micro-radian: its last point lies between two): each one's status, code and string,
      and where the arm rested.
  topic --rig R
      One JointTrajectory on /R/joint_trajectory from where the arm is to a point 0.2 rad
      away in 2 s; reports the target and where the arm is 4 s later.

The environment picks the DDS domain (ROS_DOMAIN_ID) and keeps Fast DDS on loopback
(tests/peers/fastdds_loopback.xml through FASTRTPS_DEFAULT_PROFILES_FILE).
"""

import argparse
import json
import math
import sys
import threading
import time

import rclpy
from builtin_interfaces.msg import Duration
from control_msgs.action import FollowJointTrajectory
from rclpy.action import ActionClient
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

# The line every motion goal follows, per joint (rad): inside the IRB 120's ranges from
# its home position, and clear of the shipped cell.
DELTA = [0.4, 0.15, -0.15, 0.3, 0.3, 0.5]
# Where a preempting goal goes instead (rad from the start), clear of the shipped cell too.
DELTA_PREEMPT = [0.6, 0.2, -0.2, 0.1, 0.5, 0.8]
# A preempting goal's first point, after it is sent (s): time to go on into it from the
# first goal's motion; and how long it then eases out to rest.
PREEMPT_FIRST_S = 0.5
PREEMPT_DURATION_S = 4.0
# Points of a goal: one every this many seconds.
POINT_EVERY_S = 0.1
# How long the arm must hold still to be at rest, and how still (rad).
REST_S = 0.5
REST_RAD = 1e-6


def duration(t):
    sec = math.floor(t)
    return Duration(sec=int(sec), nanosec=int(round((t - sec) * 1e9)) % 1_000_000_000)


def wait(future, timeout_s):
    end = time.monotonic() + timeout_s
    while not future.done():
        if time.monotonic() > end:
            raise TimeoutError("no answer")
        time.sleep(0.005)
    return future.result()


class Peer:
    def __init__(self, rig):
        self.node = Node("fjt_client")
        self.names = None
        self.position = None
        self.lock = threading.Lock()
        qos = QoSProfile(
            depth=10,
            history=HistoryPolicy.KEEP_LAST,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.VOLATILE,
        )
        self.node.create_subscription(JointState, f"/{rig}/joint_states", self.on_state, qos)
        self.client = ActionClient(self.node, FollowJointTrajectory, f"/{rig}/follow_joint_trajectory")
        self.topic = self.node.create_publisher(JointTrajectory, f"/{rig}/joint_trajectory", qos)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.spinning = threading.Thread(target=self.executor.spin)
        self.spinning.start()

    def close(self):
        # The spinning thread joined before rclpy shuts down: a C++ thread left running at
        # exit aborts the process.
        self.executor.shutdown(timeout_sec=1.0)
        self.spinning.join()
        self.node.destroy_node()
        rclpy.try_shutdown()

    def on_state(self, message):
        with self.lock:
            self.names = list(message.name)
            self.position = list(message.position)

    def now(self):
        with self.lock:
            return list(self.position) if self.position is not None else None

    def wait_for_state(self, timeout_s):
        end = time.monotonic() + timeout_s
        while self.now() is None:
            if time.monotonic() > end:
                raise TimeoutError("no joint state")
            time.sleep(0.01)
        return self.now()

    def at_rest(self, timeout_s):
        """The position once it held still for REST_S."""
        end = time.monotonic() + timeout_s
        last, since = self.now(), time.monotonic()
        while time.monotonic() < end:
            time.sleep(0.02)
            now = self.now()
            if max(abs(a - b) for a, b in zip(now, last)) > REST_RAD:
                last, since = now, time.monotonic()
            elif time.monotonic() - since >= REST_S:
                return now
        raise TimeoutError("the arm did not come to rest")

    def line_goal(self, start, end, duration_s):
        """Points along the straight line from start to end, at rest at both ends."""
        goal = FollowJointTrajectory.Goal()
        goal.trajectory.joint_names = self.names
        steps = int(round(duration_s / POINT_EVERY_S))
        for i in range(1, steps + 1):
            u = i / steps
            s = u * u * (3.0 - 2.0 * u)
            point = JointTrajectoryPoint()
            point.positions = [a + s * (b - a) for a, b in zip(start, end)]
            point.time_from_start = duration(i * POINT_EVERY_S)
            goal.trajectory.points.append(point)
        return goal

    def run(self, goal, cancel_after_s=None, timeout_s=60.0):
        arrivals = []
        feedback = []

        def on_feedback(message):
            arrivals.append(time.monotonic())
            feedback.append(message.feedback)

        sent = time.monotonic()
        handle = wait(self.client.send_goal_async(goal, feedback_callback=on_feedback), timeout_s)
        answered_s = time.monotonic() - sent
        out = {"accepted": handle.accepted, "answered_s": answered_s}
        if not handle.accepted:
            return out
        result_future = handle.get_result_async()
        if cancel_after_s is not None:
            time.sleep(cancel_after_s)
            response = wait(handle.cancel_goal_async(), 10.0)
            out["cancel_return_code"] = response.return_code
            out["canceling"] = len(response.goals_canceling)
        result = wait(result_future, timeout_s)
        out.update(
            {
                "status": result.status,
                "error_code": result.result.error_code,
                "error_string": result.result.error_string,
                "feedback": len(arrivals),
                "seconds": time.monotonic() - sent,
            }
        )
        if len(arrivals) > 1:
            gaps = [b - a for a, b in zip(arrivals, arrivals[1:])]
            out["feedback_hz"] = (len(arrivals) - 1) / (arrivals[-1] - arrivals[0])
            out["feedback_max_gap_s"] = max(gaps)
            last = feedback[-1]
            out["feedback_names"] = list(last.joint_names)
            out["last_desired"] = list(last.desired.positions)
            out["last_actual"] = list(last.actual.positions)
            out["last_error"] = list(last.error.positions)
        return out


def place_on_line(start, end, at):
    """Where `at` is along the line start-end (0..1) and how far from it (rad)."""
    d = [b - a for a, b in zip(start, end)]
    p = [x - a for a, x in zip(start, at)]
    s = sum(x * y for x, y in zip(p, d)) / sum(x * x for x in d)
    off = math.sqrt(sum((x - s * y) ** 2 for x, y in zip(p, d)))
    return s, off


def refusals(peer):
    before = peer.wait_for_state(20.0)
    names = peer.names
    out = {}

    def goal_of(points, joint_names=None):
        goal = FollowJointTrajectory.Goal()
        goal.trajectory.joint_names = joint_names or names
        goal.trajectory.points = points
        return goal

    def point(positions, t):
        return JointTrajectoryPoint(positions=positions, time_from_start=duration(t))

    wrong = list(names)
    wrong[2] = "elbow"
    out["wrong_joint"] = peer.run(goal_of([point(before, 1.0)], wrong))
    nan = list(before)
    nan[1] = float("nan")
    out["nan"] = peer.run(goal_of([point(before, 0.5), point(nan, 1.0)]))
    out["non_increasing"] = peer.run(goal_of([point(before, 1.0), point(before, 1.0)]))
    made = time.monotonic()
    million = [point(before, 0.001 * (i + 1)) for i in range(1_000_000)]
    out["million_built_s"] = time.monotonic() - made
    out["million"] = peer.run(goal_of(million), timeout_s=300.0)
    time.sleep(1.0)
    after = peer.now()
    out["moved_rad"] = max(abs(a - b) for a, b in zip(before, after))
    return out


def motion(peer, duration_s):
    start = peer.wait_for_state(20.0)
    end = [a + d for a, d in zip(start, DELTA)]
    out = {"start": start, "end": end}
    out["complete"] = peer.run(peer.line_goal(start, end, duration_s), timeout_s=duration_s * 3)
    reached = peer.at_rest(10.0)
    out["reached"] = reached
    # Back along the same line, canceled at half of it.
    out["cancel"] = peer.run(
        peer.line_goal(reached, start, duration_s),
        cancel_after_s=duration_s / 2,
        timeout_s=duration_s * 3,
    )
    rest = peer.at_rest(10.0)
    out["rest"] = rest
    out["rest_along"], out["rest_off_rad"] = place_on_line(reached, start, rest)
    return out


def ease_out_goal(peer, start, end, first_s, duration_s):
    """Points from start toward end, the first at first_s, easing out to rest at end
    (1 - (1 - u)^3 of the way at u of duration_s)."""
    goal = FollowJointTrajectory.Goal()
    goal.trajectory.joint_names = peer.names
    steps = int(round(duration_s / POINT_EVERY_S))
    for i in range(1, steps + 1):
        u = i / steps
        s = 1.0 - (1.0 - u) ** 3
        point = JointTrajectoryPoint()
        point.positions = [a + s * (b - a) for a, b in zip(start, end)]
        point.time_from_start = duration(first_s + (i - 1) * POINT_EVERY_S)
        goal.trajectory.points.append(point)
    return goal


def preempt(peer, duration_s):
    start = peer.wait_for_state(20.0)
    end = [a + d for a, d in zip(start, DELTA)]
    other = [a + d for a, d in zip(start, DELTA_PREEMPT)]
    out = {"start": start, "end": end, "other_end": other}
    t0 = time.monotonic()
    handle = wait(peer.client.send_goal_async(peer.line_goal(start, end, duration_s)), 10.0)
    out["first_accepted"] = handle.accepted
    first_result = handle.get_result_async()
    time.sleep(0.4 * duration_s - (time.monotonic() - t0))
    now = peer.now()
    out["second_from"] = now
    out["second_sent_s"] = time.monotonic() - t0
    goal = ease_out_goal(peer, now, other, PREEMPT_FIRST_S, PREEMPT_DURATION_S)
    out["second"] = peer.run(goal, timeout_s=3 * (PREEMPT_FIRST_S + PREEMPT_DURATION_S))
    result = wait(first_result, 10.0)
    out["first"] = {
        "status": result.status,
        "error_code": result.result.error_code,
        "error_string": result.result.error_string,
    }
    out["second_end"] = peer.at_rest(10.0)
    return out


def tolerances(peer):
    from control_msgs.msg import JointTolerance

    start = peer.wait_for_state(20.0)
    end = [a + d for a, d in zip(start, DELTA)]
    out = {"start": start}
    goal = peer.line_goal(start, end, 2.0)
    goal.path_tolerance = [JointTolerance(name=peer.names[5], position=1e-3)]
    out["path"] = peer.run(goal, timeout_s=20.0)
    rest = peer.at_rest(10.0)
    out["path_rest"] = rest
    out["path_rest_along"], out["path_rest_off_rad"] = place_on_line(start, end, rest)
    # joint_1 ends half a micro-radian off the wire's grid; the rest stay where they are.
    target = list(rest)
    target[0] = round(rest[0] + 0.1, 6) + 5e-7
    goal = peer.line_goal(rest, target, 2.0)
    goal.goal_tolerance = [JointTolerance(name=peer.names[0], position=1e-7)]
    out["goal"] = peer.run(goal, timeout_s=20.0)
    out["goal_target"] = target
    out["goal_rest"] = peer.at_rest(10.0)
    return out


def topic(peer):
    start = peer.wait_for_state(20.0)
    target = [a + 0.2 for a in start]
    message = JointTrajectory()
    message.joint_names = peer.names
    message.points = [
        JointTrajectoryPoint(positions=start, time_from_start=duration(0.0)),
        JointTrajectoryPoint(positions=target, time_from_start=duration(2.0)),
    ]
    peer.topic.publish(message)
    time.sleep(4.0)
    return {"start": start, "target": target, "after": peer.now()}


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("mode", choices=["refusals", "motion", "preempt", "tolerances", "topic"])
    parser.add_argument("--rig", required=True)
    parser.add_argument("--duration-s", type=float, default=10.0)
    args = parser.parse_args()
    rclpy.init()
    peer = Peer(args.rig)
    if args.mode == "topic":
        end = time.monotonic() + 20.0
        while peer.topic.get_subscription_count() == 0:
            if time.monotonic() > end:
                raise TimeoutError("no subscriber of the trajectory topic")
            time.sleep(0.05)
    elif not peer.client.wait_for_server(timeout_sec=20.0):
        raise TimeoutError("no FollowJointTrajectory server")
    print("ready", flush=True)
    if args.mode == "refusals":
        out = refusals(peer)
    elif args.mode == "motion":
        out = motion(peer, args.duration_s)
    elif args.mode == "preempt":
        out = preempt(peer, args.duration_s)
    elif args.mode == "tolerances":
        out = tolerances(peer)
    else:
        out = topic(peer)
    print(json.dumps(out), flush=True)
    peer.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
