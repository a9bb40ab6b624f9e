"""A ROS 2 peer over Zenoh that rigbridge did not write: PyPI's eclipse-zenoh for the
session and rosbags for the CDR messages and the RIHS01 type hashes. Used by tests/ros2.rs.

  listen  --endpoint E [--seconds S] [--rigs N] [--wait-end]
      listens on E (peer mode), takes every `<domain>/*/joint_states/...` sample, decodes it
      with rosbags and its attachment with zenoh.ext; once it has seen N rigs it counts for S
      seconds, asks the liveliness tokens, then (--wait-end) waits for the samples to stop
      (1 s of silence) and prints one JSON object per rig and the tokens.
  trajectory --endpoint E --rig R --joints j1,j2,.. --send P [--send P ..]
             [--connect] [--user U --password-file F] [--token-timeout S] [--gap S]
      listens on E (or, with --connect, connects to the router at E as a client, logged in
      as U with the password in F when given), waits up to S seconds for R's
      JointTrajectory subscription token, then publishes one JointTrajectory for each P in
      order, --gap seconds apart (also when no subscription came: a peer that sends
      anyway). P: `t:q1,q2,..;t:q1,..` (s, rad). Prints whether the subscription and the
      node's token were seen and how many of R's JointState samples arrived; or, when the
      session cannot be opened (the router refused the login), `opened: false` and why.
  servo --endpoint E --rig R [--connect] [--user U --password-file F] [--token-timeout S]
        [--servo-deg D] [--seconds S] [--bad]
      as `trajectory` opens its session and waits for R's node, then puts servo targets
      on the key `R/servo` at 100 Hz for S seconds: joint_1 from 0 to D degrees (a smooth
      step over the first two thirds, then held), the other joints at the IRB 120's rest
      (0, 0, 0, 0, 30, 0 deg), each `{"joints_deg": [..], "sent_s": t}`; with --bad, one
      more with joint_3 at 80 deg (outside its limits). Prints what it sent.
  router --endpoint E --dictionary F
      a Zenoh router listening on E that admits only sessions logging in with a
      `user:password` line of F (Zenoh's usrpwd authentication); runs until killed.
Prints `ready` on its own line once listening (or once the open was tried, with --connect).
"""

import argparse
import json
import sys
import time

import zenoh
from zenoh.ext import Int64, z_deserialize, z_serialize
from rosbags.typesys import Stores, get_typestore

TYPES = get_typestore(Stores.ROS2_JAZZY)
STATE = "sensor_msgs/msg/JointState"
TRAJECTORY = "trajectory_msgs/msg/JointTrajectory"


def open_listening(endpoint):
    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("listen/endpoints", json.dumps([endpoint]))
    config.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(config)
    print("ready", flush=True)
    return session


def tokens(session, domain):
    replies = session.liveliness().get(f"@ros2_lv/{domain}/**", timeout=3.0)
    return sorted(str(reply.ok.key_expr) for reply in replies if reply.ok is not None)


def decode_attachment(attachment):
    fields = z_deserialize(tuple[str, Int64, str, Int64, str, bytes], attachment)
    keys = (fields[0], fields[2], fields[4])
    assert keys == ("sequence_number", "source_timestamp", "source_gid"), keys
    return int(fields[1]), int(fields[3]), fields[5].hex()


def listen(args):
    session = open_listening(args.endpoint)
    subscriber = session.declare_subscriber(f"{args.domain}/*/joint_states/**")
    rigs = {}
    started = None
    asked = None
    last = time.monotonic()
    deadline = time.monotonic() + args.timeout
    while time.monotonic() < deadline:
        sample = subscriber.try_recv()
        now = time.monotonic()
        if asked is not None and not args.wait_end:
            break
        if sample is None:
            if started is not None and asked is not None and now - last > 1.0:
                break
            time.sleep(0.0005)
            continue
        last = now
        key = str(sample.key_expr)
        rig = key.split("/")[1]
        message = TYPES.deserialize_cdr(sample.payload.to_bytes(), STATE)
        sequence, stamp_ns, gid = decode_attachment(sample.attachment)
        entry = rigs.setdefault(rig, {"key": key, "count": 0, "in_window": 0, "sequences": [],
                                      "gids": set(), "stamp_mismatch": 0, "distinct": set()})
        entry["count"] += 1
        entry["sequences"].append(sequence)
        entry["gids"].add(gid)
        header_ns = message.header.stamp.sec * 10**9 + message.header.stamp.nanosec
        entry["stamp_mismatch"] += header_ns != stamp_ns
        entry["names"] = list(message.name)
        entry["last_position"] = [float(p) for p in message.position]
        entry["distinct"].add(tuple(round(float(p), 9) for p in message.position))
        if started is None and len(rigs) >= args.rigs:
            started = now
        if started is not None and asked is None:
            if now - started <= args.seconds:
                entry["in_window"] += 1
            else:
                asked = tokens(session, args.domain)
    out = {"rigs": {}, "tokens": asked or [], "window_s": args.seconds,
           "rosbags_hash": TYPES.hash_rihs01(STATE)}
    for rig, entry in rigs.items():
        sequences = entry["sequences"]
        out["rigs"][rig] = {
            "key": entry["key"], "count": entry["count"],
            "rate_hz": entry["in_window"] / args.seconds,
            "names": entry["names"], "last_position": entry["last_position"],
            "distinct_positions": len(entry["distinct"]),
            "sequences_consecutive": sequences == list(range(sequences[0], sequences[0] + len(sequences))),
            "gids": sorted(entry["gids"]), "stamp_mismatch": entry["stamp_mismatch"],
        }
    session.close()
    print(json.dumps(out), flush=True)


def trajectory_message(joints, spec):
    Header = TYPES.types["std_msgs/msg/Header"]
    Time = TYPES.types["builtin_interfaces/msg/Time"]
    Duration = TYPES.types["builtin_interfaces/msg/Duration"]
    Point = TYPES.types["trajectory_msgs/msg/JointTrajectoryPoint"]
    Trajectory = TYPES.types[TRAJECTORY]
    import numpy
    points = []
    for item in spec.split(";"):
        t, values = item.split(":")
        seconds = float(t)
        points.append(Point(
            positions=numpy.array([float(v) for v in values.split(",")], dtype=numpy.float64),
            velocities=numpy.array([], dtype=numpy.float64),
            accelerations=numpy.array([], dtype=numpy.float64),
            effort=numpy.array([], dtype=numpy.float64),
            time_from_start=Duration(sec=int(seconds), nanosec=int(round((seconds % 1) * 1e9)))))
    message = Trajectory(header=Header(stamp=Time(sec=0, nanosec=0), frame_id=""),
                         joint_names=joints, points=points)
    return bytes(TYPES.serialize_cdr(message, TRAJECTORY))


def open_client(args):
    """A client session to the router at the endpoint, logged in when asked; None and why
    when the router does not admit it."""
    config = zenoh.Config()
    config.insert_json5("mode", '"client"')
    config.insert_json5("connect/endpoints", json.dumps([args.endpoint]))
    config.insert_json5("scouting/multicast/enabled", "false")
    if args.user is not None:
        with open(args.password_file) as f:
            password = f.read().strip()
        config.insert_json5("transport/auth/usrpwd",
                            json.dumps({"user": args.user, "password": password}))
    try:
        session = zenoh.open(config)
    except zenoh.ZError as e:
        print("ready", flush=True)
        return None, str(e)
    print("ready", flush=True)
    return session, None


def trajectory(args):
    if args.connect:
        session, refused = open_client(args)
        if session is None:
            print(json.dumps({"opened": False, "error": refused}), flush=True)
            return
    else:
        session = open_listening(args.endpoint)
    states = session.declare_subscriber(f"{args.domain}/{args.rig}/joint_states/**")
    deadline = time.monotonic() + args.token_timeout
    wanted = f"%{args.rig}%joint_trajectory/trajectory_msgs::msg::dds_::JointTrajectory_/"
    node = f"/NN/%/%{args.rig}/rigbridge"
    seen = []
    while time.monotonic() < deadline:
        seen = tokens(session, args.domain)
        if any("/MS/" in t and wanted in t for t in seen):
            break
        time.sleep(0.2)
    subscribed = any("/MS/" in t and wanted in t for t in seen)
    key = (f"{args.domain}/{args.rig}/joint_trajectory/"
           f"trajectory_msgs::msg::dds_::JointTrajectory_/{TYPES.hash_rihs01(TRAJECTORY)}")
    joints = args.joints.split(",")
    gid = bytes(range(16))
    for sequence, spec in enumerate(args.send, start=1):
        attachment = z_serialize(("sequence_number", Int64(sequence), "source_timestamp",
                                  Int64(time.time_ns()), "source_gid", gid))
        session.put(key, trajectory_message(joints, spec), attachment=attachment)
        time.sleep(args.gap)
    received = 0
    while states.try_recv() is not None:
        received += 1
    session.close()
    print(json.dumps({"opened": True, "sent": len(args.send), "key": key,
                      "subscribed": subscribed, "node_seen": any(t.endswith(node) for t in seen),
                      "joint_states": received}), flush=True)


SERVO_RATE_HZ = 100.0


def servo(args):
    if args.connect:
        session, refused = open_client(args)
        if session is None:
            print(json.dumps({"opened": False, "error": refused}), flush=True)
            return
    else:
        session = open_listening(args.endpoint)
    node = f"/NN/%/%{args.rig}/rigbridge"
    deadline = time.monotonic() + args.token_timeout
    seen = []
    while time.monotonic() < deadline and not any(t.endswith(node) for t in seen):
        seen = tokens(session, args.domain)
        time.sleep(0.2)
    # The node's subscriptions are declared with its token; a moment for them to reach us.
    time.sleep(0.5)
    key = f"{args.rig}/servo"
    messages = int(args.seconds * SERVO_RATE_HZ)
    ramp = 2.0 / 3.0 * args.seconds
    start = time.monotonic()
    for m in range(messages):
        t = m / SERVO_RATE_HZ
        time.sleep(max(0.0, start + t - time.monotonic()))
        s = min(t / ramp, 1.0)
        joint_1 = args.servo_deg * s * s * (3.0 - 2.0 * s)
        session.put(key, json.dumps({"joints_deg": [joint_1, 0.0, 0.0, 0.0, 30.0, 0.0],
                                     "sent_s": t}))
    sent = messages
    if args.bad:
        session.put(key, json.dumps({"joints_deg": [args.servo_deg, 0.0, 80.0, 0.0, 30.0, 0.0],
                                     "sent_s": messages / SERVO_RATE_HZ}))
        sent += 1
    time.sleep(0.2)
    session.close()
    print(json.dumps({"opened": True, "key": key, "sent": sent,
                      "node_seen": any(t.endswith(node) for t in seen)}), flush=True)


def router(args):
    config = zenoh.Config()
    config.insert_json5("mode", '"router"')
    config.insert_json5("listen/endpoints", json.dumps([args.endpoint]))
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(args.dictionary))
    session = zenoh.open(config)
    print("ready", flush=True)
    time.sleep(args.timeout)
    session.close()


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("mode", choices=["listen", "trajectory", "servo", "router"])
    parser.add_argument("--endpoint", required=True)
    parser.add_argument("--domain", type=int, default=0)
    parser.add_argument("--seconds", type=float, default=2.0)
    parser.add_argument("--rigs", type=int, default=1)
    parser.add_argument("--wait-end", action="store_true")
    parser.add_argument("--timeout", type=float, default=60.0)
    parser.add_argument("--rig")
    parser.add_argument("--joints")
    parser.add_argument("--send", action="append", default=[])
    parser.add_argument("--gap", type=float, default=1.5)
    parser.add_argument("--token-timeout", type=float, default=60.0)
    parser.add_argument("--connect", action="store_true")
    parser.add_argument("--user")
    parser.add_argument("--password-file")
    parser.add_argument("--dictionary")
    parser.add_argument("--servo-deg", type=float, default=10.0)
    parser.add_argument("--bad", action="store_true")
    args = parser.parse_args()
    {"listen": listen, "trajectory": trajectory, "servo": servo,
     "router": router}[args.mode](args)


if __name__ == "__main__":
    sys.exit(main())
