"""An EGM sensor that holds a robot's messages to what abb_libegm requires, written from
abb_libegm's source (github.com/ros-industrial/abb_libegm), not from rigbridge's. Driven by
tests/egm.rs against rigbridge's EGM twin.

What abb_libegm requires, as read in its source:
- src/egm_base_interface.cpp, InputContainer::parseFromArray: a message that parses is a
  session's first when it is the first received or its header seqno is 0; then
  initializeCallback applies a pending configuration, and OutputContainer::prepareOutputs
  numbers the replies from 0 again (sequence_number_ = 0 on a first message, else + 1) and
  starts the outputs from the feedback.
- src/egm_base_interface.cpp, InputContainer::extractParsedInformation: the message is used
  only if parse() succeeds for the header, feedBack, planned and the status; otherwise
  initializeCallback fails and the reply is empty, which src/egm_udp_server.cpp does not send.
- src/egm_common_auxiliary.cpp, parse(wrapper::Header*, ...): seqno, tm and mtype present and
  mtype MSGTYPE_DATA.
- parse(wrapper::Feedback*, ...) and parse(wrapper::Planned*, ...): the robot's joints (six of
  them, for a six-axis robot: parse(wrapper::Joints*, ...)'s `Six` case), then (robot axes
  other than None) the cartesian pose, then the time (parse(wrapper::Clock*, ...): sec and
  usec).
- parse(wrapper::CartesianPose*, ...): pos with x, y and z, and orient with u0, u1, u2 and u3;
  euler is optional (converted from the quaternion when absent).
- parse(wrapper::Status*, ...): motorState, mciState and rapidExecState each with its state,
  and mciConvergenceMet.
- InputContainer::statesOk: motors on, RAPID running (or undefined) and EGM running; the
  controller interface (src/egm_controller_interface.cpp, callback) takes new outputs from the
  user only then, and ControllerMotion::readOutputs keeps the previous outputs when the user's
  write is late (it times out): the same reply again.
- InputContainer::estimateSampleTime: the feedback times' difference, floored to whole ms,
  no lower than 4 ms (Constants::RobotController::LOWEST_SAMPLE_TIME, src/egm_common.cpp).

Usage: libegm_sensor.py SECONDS REPEAT_EVERY AMPLITUDE_DEG DUMP_PATH
Prints its UDP port, then `timed out` once its silence has ended the first session, then one
JSON report. Every EgmRobot's joints and poses go to DUMP_PATH, one JSON line each.
"""
import json
import math
import socket
import sys

from abb_robot_client._egm_protobuf import egm_pb2

# egm_common.cpp: Constants::RobotController::LOWEST_SAMPLE_TIME, DEFAULT_NUMBER_OF_ROBOT_JOINTS.
LOWEST_SAMPLE_TIME_S = 0.004
ROBOT_JOINTS = 6
# Joint 1's sine: period of the motion.
SINE_PERIOD_S = 4.0
# How long the sensor stays silent at most, waiting for the controller's CommTimeout.
SILENCE_LIMIT_S = 10.0

seconds = float(sys.argv[1])
repeat_every = int(sys.argv[2])
amplitude = float(sys.argv[3])
dump = open(sys.argv[4], "w")

sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
sock.bind(("127.0.0.1", 0))
sock.settimeout(5.0)
print(sock.getsockname()[1], flush=True)


def pose_ok(pose):
    if not pose.HasField("pos") or not pose.HasField("orient"):
        return False
    pos, orient = pose.pos, pose.orient
    return all(pos.HasField(f) for f in "xyz") and all(
        orient.HasField(f) for f in ("u0", "u1", "u2", "u3")
    )


def joints_ok(part):
    return part.HasField("joints") and len(part.joints.joints) == ROBOT_JOINTS


def clock_ok(part):
    return part.HasField("time") and part.time.HasField("sec") and part.time.HasField("usec")


def problems(robot):
    """What abb_libegm's parse() calls would refuse in this message."""
    found = []
    header = robot.header
    if not (robot.HasField("header") and header.HasField("seqno") and header.HasField("tm")
            and header.HasField("mtype")):
        found.append("header without seqno, tm or mtype")
    elif header.mtype != egm_pb2.EgmHeader.MSGTYPE_DATA:
        found.append("header mtype not MSGTYPE_DATA")
    for name in ("feedBack", "planned"):
        part = getattr(robot, name)
        if not robot.HasField(name):
            found.append(f"no {name}")
            continue
        if not joints_ok(part):
            found.append(f"{name}.joints not six values")
        if not (part.HasField("cartesian") and pose_ok(part.cartesian)):
            found.append(f"{name}.cartesian without pos x, y, z and orient u0..u3")
        if not clock_ok(part):
            found.append(f"{name}.time without sec and usec")
    for name in ("motorState", "mciState", "rapidExecState"):
        if not (robot.HasField(name) and getattr(robot, name).HasField("state")):
            found.append(f"no {name}.state")
    if not robot.HasField("mciConvergenceMet"):
        found.append("no mciConvergenceMet")
    return found


def states_ok(robot):
    rapid = robot.rapidExecState.state
    return (robot.motorState.state == egm_pb2.EgmMotorState.MOTORS_ON
            and rapid in (egm_pb2.EgmRapidCtrlExecState.RAPID_UNDEFINED,
                          egm_pb2.EgmRapidCtrlExecState.RAPID_RUNNING)
            and robot.mciState.state == egm_pb2.EgmMCIState.MCI_RUNNING)


def time_us(robot):
    t = robot.feedBack.time
    return t.sec * 1_000_000 + t.usec


def pose_list(pose):
    return [pose.pos.x, pose.pos.y, pose.pos.z,
            pose.orient.u0, pose.orient.u1, pose.orient.u2, pose.orient.u3]


report = {
    "messages": 0,
    "refused": 0,
    "problems": {},
    "sessions": [],
    "seqno_gaps": 0,
    "time_not_advancing": 0,
    "sample_time_ms": [None, None],
    "replies": 0,
    "repeats": 0,
    "not_running_while_replying": 0,
}
state = {"first_call": True, "reply_seqno": 0, "last": None, "last_reply": None,
         "start": None, "cycle": 0}


def receive():
    data, address = sock.recvfrom(4096)
    robot = egm_pb2.EgmRobot()
    robot.ParseFromString(data)
    report["messages"] += 1
    found = problems(robot)
    if found:
        report["refused"] += 1
        for p in found:
            report["problems"][p] = report["problems"].get(p, 0) + 1
        return None, address
    first = state["first_call"] or robot.header.seqno == 0
    state["first_call"] = False
    last = state["last"]
    if first:
        report["sessions"].append({"first_seqno": robot.header.seqno,
                                   "rapid": robot.rapidExecState.state,
                                   "mci": robot.mciState.state})
        state["reply_seqno"] = 0
        state["start"] = list(robot.feedBack.joints.joints)
        state["cycle"] = 0
        state["last_reply"] = None
    elif last is not None:
        if robot.header.seqno != last.header.seqno + 1:
            report["seqno_gaps"] += 1
        step_us = time_us(robot) - time_us(last)
        if step_us <= 0:
            report["time_not_advancing"] += 1
        sample_ms = max(math.floor(step_us / 1000.0), LOWEST_SAMPLE_TIME_S * 1000)
        low, high = report["sample_time_ms"]
        report["sample_time_ms"] = [sample_ms if low is None else min(low, sample_ms),
                                    sample_ms if high is None else max(high, sample_ms)]
    if not first:
        state["reply_seqno"] += 1
    state["last"] = robot
    dump.write(json.dumps({
        "seqno": robot.header.seqno,
        "feedback_joints": list(robot.feedBack.joints.joints),
        "feedback_pose": pose_list(robot.feedBack.cartesian),
        "planned_joints": list(robot.planned.joints.joints),
        "planned_pose": pose_list(robot.planned.cartesian),
    }) + "\n")
    return robot, address


def reply(address, joints, speeds):
    sensor = egm_pb2.EgmSensor()
    sensor.header.seqno = state["reply_seqno"]
    sensor.header.tm = 0
    sensor.header.mtype = egm_pb2.EgmHeader.MSGTYPE_CORRECTION
    sensor.planned.joints.joints.extend(joints)
    sensor.speedRef.joints.joints.extend(speeds)
    sock.sendto(sensor.SerializeToString(), address)
    report["replies"] += 1


def command(cycle):
    """Joint 1 on a sine about where the session started; the others held."""
    t = cycle * LOWEST_SAMPLE_TIME_S
    w = 2.0 * math.pi / SINE_PERIOD_S
    joints = list(state["start"])
    speeds = [0.0] * ROBOT_JOINTS
    joints[0] += amplitude * math.sin(w * t)
    speeds[0] = amplitude * w * math.cos(w * t)
    return joints, speeds


def follow(cycles):
    """Answers `cycles` messages; every `repeat_every`-th answer repeats the last one, as
    abb_libegm does when the user's write is late."""
    done = 0
    while done < cycles:
        robot, address = receive()
        if robot is None:
            continue
        if not states_ok(robot):
            report["not_running_while_replying"] += 1
        state["cycle"] += 1
        if state["last_reply"] is not None and state["cycle"] % repeat_every == 0:
            joints, speeds = state["last_reply"]
            report["repeats"] += 1
        else:
            joints, speeds = command(state["cycle"])
        state["last_reply"] = (joints, speeds)
        reply(address, joints, speeds)
        done += 1


cycles = int(round(seconds / LOWEST_SAMPLE_TIME_S))
follow(cycles)
# Silent: the controller's CommTimeout ends the session.
silent = 0
while True:
    robot, _ = receive()
    silent += 1
    if robot is not None and robot.mciState.state != egm_pb2.EgmMCIState.MCI_RUNNING:
        report["after_timeout"] = {"mci": robot.mciState.state,
                                   "rapid": robot.rapidExecState.state,
                                   "motors": robot.motorState.state}
        break
    if silent * LOWEST_SAMPLE_TIME_S > SILENCE_LIMIT_S:
        raise SystemExit("the session did not end while the sensor was silent")
print("timed out", flush=True)
# The next session: its first message has seqno 0; answer a second of it.
while True:
    robot, address = receive()
    if robot is not None and robot.header.seqno == 0:
        break
    silent += 1
    if silent * LOWEST_SAMPLE_TIME_S > 2 * SILENCE_LIMIT_S:
        raise SystemExit("no new session began")
reply(address, state["start"], [0.0] * ROBOT_JOINTS)
follow(int(round(1.0 / LOWEST_SAMPLE_TIME_S)))
dump.close()
print(json.dumps(report), flush=True)
