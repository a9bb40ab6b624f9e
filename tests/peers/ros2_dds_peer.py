"""A real ROS 2 Jazzy node (PyPI's ros-jazzy-rclpy on Fast DDS) that listens to a rig's
topics over DDS, for tests/ros2_dds.rs. It prints "ready" once its subscriptions exist, then
one JSON line of what it received.

  listen --rig R --hz F [--gap-hz G] [--quiet-s S] [--timeout-s T]
      /R/joint_states (reliable, volatile, depth 10) until no joint state came for S
      seconds after the first (the run ended) or T seconds passed. Reports the count, the
      rate and gaps by header stamp (a gap: consecutive stamps 2 periods of G apart or
      more; G is F unless given; the gaps at 2 periods of F are reported too), the names, the last position, and what the ROS 2 graph says of the publishers
      of /tf, /tf_static and /R/robot_description (node, type, QoS). PyPI ships no
      tf2_msgs for rclpy, so /tf's content is not read here.
  late --rig R [--timeout-s T]
      /R/robot_description (transient local, depth 1), subscribed to after the rig has
      published it: reports the text.

The environment picks the DDS domain (ROS_DOMAIN_ID) and keeps Fast DDS on loopback
(tests/peers/fastdds_loopback.xml through FASTRTPS_DEFAULT_PROFILES_FILE).
"""

import argparse
import json
import sys
import time

import numpy as np
import rclpy
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import String

# A gap: consecutive stamps this many periods apart or more: a message missing (its
# neighbours are 2 periods apart), or the stream held up as long as one message. At the
# publishing rate a wake of the publisher more than one period late is one (pacing keeps the
# rate from the late wake on); at a lower rate asked of the stream it is not.
GAP_PERIODS = 2.0


def qos(depth, latched):
    return QoSProfile(
        depth=depth,
        history=HistoryPolicy.KEEP_LAST,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )


def stamp_s(header):
    return header.stamp.sec + header.stamp.nanosec * 1e-9


def publishers(node, topic):
    """What the graph says of each publisher of `topic`."""
    return [
        {
            "node": f"{p.node_namespace.rstrip('/')}/{p.node_name}",
            "type": p.topic_type,
            "reliable": p.qos_profile.reliability == ReliabilityPolicy.RELIABLE,
            "transient_local": p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL,
        }
        for p in node.get_publishers_info_by_topic(topic)
    ]


def listen(node, args):
    states = []
    node.create_subscription(JointState, f"/{args.rig}/joint_states", states.append, qos(10, False))
    print("ready", flush=True)
    start, last_count, last_change = time.monotonic(), 0, time.monotonic()
    graph = {}
    while time.monotonic() - start < args.timeout_s:
        rclpy.spin_once(node, timeout_sec=0.05)
        if len(states) != last_count:
            last_count, last_change = len(states), time.monotonic()
            if not graph and len(states) >= args.hz:
                topics = ["/tf", "/tf_static", f"/{args.rig}/robot_description", f"/{args.rig}/joint_states"]
                graph = {t: publishers(node, t) for t in topics}
        elif states and time.monotonic() - last_change > args.quiet_s:
            break
    stamps = [stamp_s(s.header) for s in states]
    intervals = np.diff(stamps) if len(stamps) > 1 else np.array([])
    period = 1.0 / args.hz
    gap_period = 1.0 / (args.gap_hz or args.hz)
    return {
        "count": len(states),
        "rate_hz": (len(stamps) - 1) / (stamps[-1] - stamps[0]) if len(stamps) > 1 else 0.0,
        "increasing": bool(np.all(intervals > 0)),
        "gaps": int(np.sum(intervals >= GAP_PERIODS * gap_period)),
        "gaps_at_publish_rate": int(np.sum(intervals >= GAP_PERIODS * period)),
        "max_interval_s": float(intervals.max()) if intervals.size else None,
        "names": list(states[-1].name) if states else [],
        "last_position": list(states[-1].position) if states else [],
        "distinct_positions": len({tuple(s.position) for s in states}),
        "graph": graph,
    }


def late(node, args):
    description = []
    node.create_subscription(String, f"/{args.rig}/robot_description", description.append, qos(1, True))
    print("ready", flush=True)
    start = time.monotonic()
    while time.monotonic() - start < args.timeout_s and not description:
        rclpy.spin_once(node, timeout_sec=0.05)
    return {
        "waited_s": time.monotonic() - start,
        "description": description[-1].data if description else None,
    }


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("mode", choices=["listen", "late"])
    parser.add_argument("--rig", required=True)
    parser.add_argument("--hz", type=float, default=125.0)
    parser.add_argument("--gap-hz", type=float, default=None)
    parser.add_argument("--quiet-s", type=float, default=1.5)
    parser.add_argument("--timeout-s", type=float, default=60.0)
    args = parser.parse_args()
    rclpy.init()
    node = Node("rigbridge_test_peer")
    result = listen(node, args) if args.mode == "listen" else late(node, args)
    node.destroy_node()
    rclpy.shutdown()
    print(json.dumps(result), flush=True)


if __name__ == "__main__":
    sys.exit(main())
