"""A reader we did not write, on a rigbridge run log: PyPI's `mcap` with
`mcap-protobuf-support` decodes every `/tf` message (protobuf foxglove.FrameTransforms),
composes the transforms from the base frame to the tool frame, and pairs each with the
actual positions logged at the same time (the JSON joint_state channel).

Usage: foxglove_log.py LOG.mcap BASE_FRAME TOOL_FRAME
Prints one JSON line per /tf message: {"log_time", "positions", "tool": [x, y, z],
"rotation": [w, x, y, z]}, then one summary line: {"summary": {...}} with the /tf count,
first and last log times, the attachment names and the links of robot_description.urdf.
Driven by tests/foxglove.rs.
"""
import json
import sys
import xml.etree.ElementTree as ET

from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory


def quat_mul(a, b):
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def rotate(q, v):
    w, x, y, z = q
    p = quat_mul(quat_mul(q, (0.0, *v)), (w, -x, -y, -z))
    return p[1:]


def compose(frames, base, tool):
    """The tool frame in the base frame: walk child -> parent up from the tool, then apply
    the transforms from the base down (parent_T_child, child origins and rotations)."""
    chain = []
    frame = tool
    while frame != base:
        if frame not in frames:
            raise SystemExit(f"/tf has no parent for frame {frame}")
        parent, translation, rotation = frames[frame]
        chain.append((translation, rotation))
        frame = parent
    position, orientation = (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)
    for translation, rotation in reversed(chain):
        moved = rotate(orientation, translation)
        position = tuple(p + m for p, m in zip(position, moved))
        orientation = quat_mul(orientation, rotation)
    return position, orientation


def main():
    path, base, tool = sys.argv[1:4]
    factory = DecoderFactory()
    decoders = {}
    states = {}
    transforms = []
    with open(path, "rb") as stream:
        reader = make_reader(stream)
        for schema, channel, message in reader.iter_messages():
            if channel.topic == "/tf":
                if channel.id not in decoders:
                    decoders[channel.id] = factory.decoder_for(channel.message_encoding, schema)
                transforms.append((message.log_time, decoders[channel.id](message.data)))
            elif channel.topic.endswith("/joint_state"):
                states[message.log_time] = json.loads(message.data)["position"]
        stream.seek(0)
        attachments = {a.name: a.data for a in make_reader(stream).iter_attachments()}
    for log_time, tf in transforms:
        frames = {}
        for t in tf.transforms:
            r, v = t.rotation, t.translation
            frames[t.child_frame_id] = (t.parent_frame_id, (v.x, v.y, v.z), (r.w, r.x, r.y, r.z))
        position, orientation = compose(frames, base, tool)
        print(json.dumps({
            "log_time": log_time,
            "positions": states.get(log_time),
            "tool": position,
            "rotation": orientation,
        }))
    urdf = attachments.get("robot_description.urdf")
    links = None
    if urdf is not None:
        root = ET.fromstring(urdf)
        if root.tag == "robot":
            links = [link.get("name") for link in root.findall("link")]
    times = [t for t, _ in transforms]
    print(json.dumps({"summary": {
        "tf_messages": len(transforms),
        "first_log_time": min(times) if times else None,
        "last_log_time": max(times) if times else None,
        "attachments": sorted(attachments),
        "urdf_links": links,
    }}))


if __name__ == "__main__":
    main()
