"""A client we did not write the protocol stack of: PyPI's `websockets`, speaking Foxglove's
ws-protocol (https://github.com/foxglove/ws-protocol/blob/main/docs/spec.md, subprotocol
foxglove.websocket.v1) to `rigbridge serve`'s live Foxglove server. It takes the
serverInfo and the advertise, builds protobuf classes from the advertised schemas
(FileDescriptorSets, with PyPI's `protobuf`), subscribes to /tf, /joint_states and /scene,
counts and decodes messages for a while, fetches the URDF asset, tries to publish (the
server must refuse) and finally sends an oversized message (the server must close, 1009).

Usage: foxglove_ws.py URL SECONDS BASE_FRAME TOOL_FRAME URDF_URI
Prints one JSON object: the handshake, the /tf count and time span, one row per /tf message
that has a /joint_states message of the same timestamp ({"stamp", "positions", "tool"}),
the transforms' worst quaternion norm error, scene entity ids, the largest message of each
channel (bytes, with its 13-byte header), the asset's size and the
replies to the publish and the oversized message. Driven by tests/foxglove_live.rs.
"""
import asyncio
import base64
import json
import struct
import sys
import time

import websockets
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

from foxglove_log import compose

SUBPROTOCOL = "foxglove.websocket.v1"
# Spec: server binary opcodes.
MESSAGE_DATA, FETCH_ASSET_RESPONSE = 1, 4


def message_class(channel):
    """The protobuf class of a channel, from its base64 FileDescriptorSet."""
    files = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
    pool = descriptor_pool.DescriptorPool()
    for file in files.file:
        pool.Add(file)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))


def connect(url):
    """A ws-protocol session with the server at `url` (messages up to 16 MiB: /scene's
    meshes)."""
    return websockets.connect(url, subprotocols=[SUBPROTOCOL], max_size=2**24)


async def received_until(ws, deadline):
    """The messages `ws` receives until `deadline` (`time.monotonic()`)."""
    while time.monotonic() < deadline:
        try:
            yield await asyncio.wait_for(ws.recv(), deadline - time.monotonic())
        except asyncio.TimeoutError:
            return


def stamp_ns(stamp):
    return stamp.seconds * 1_000_000_000 + stamp.nanos


async def run(url, seconds, base, tool, urdf_uri):
    out = {}
    async with connect(url) as ws:
        out["subprotocol"] = ws.subprotocol
        info = json.loads(await ws.recv())
        advertise = json.loads(await ws.recv())
        out["server_info"] = info
        out["topics"] = [c["topic"] for c in advertise["channels"]]
        by_topic = {c["topic"].rsplit("/", 1)[-1]: c for c in advertise["channels"]}
        classes = {}
        subscriptions = []
        for sub_id, name in enumerate(["tf", "joint_states", "scene"]):
            if name in by_topic:
                classes[sub_id] = (name, message_class(by_topic[name]))
                subscriptions.append({"id": sub_id, "channelId": by_topic[name]["id"]})
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))

        tf, joints, scene_ids, statuses, sizes = {}, {}, set(), [], {}
        tf_count, first, last = 0, None, None
        async for raw in received_until(ws, time.monotonic() + seconds):
            if isinstance(raw, str):
                statuses.append(json.loads(raw))
                continue
            assert raw[0] == MESSAGE_DATA, raw[0]
            sub_id, receive_ns = struct.unpack_from("<IQ", raw, 1)
            name, cls = classes[sub_id]
            sizes[name] = max(sizes.get(name, 0), len(raw))
            message = cls.FromString(raw[13:])
            if name == "tf":
                tf_count += 1
                now = time.monotonic()
                first = first if first is not None else now
                last = now
                frames = {
                    t.child_frame_id: (
                        t.parent_frame_id,
                        (t.translation.x, t.translation.y, t.translation.z),
                        (t.rotation.w, t.rotation.x, t.rotation.y, t.rotation.z),
                    )
                    for t in message.transforms
                }
                tf[stamp_ns(message.transforms[0].timestamp)] = frames
            elif name == "joint_states":
                joints[stamp_ns(message.timestamp)] = [j.position for j in message.joints]
            else:
                scene_ids.update(e.id for e in message.entities)
        out["tf_count"] = tf_count
        out["tf_span_s"] = (last - first) if tf_count > 1 else 0.0
        out["window_s"] = seconds
        quat_error = 0.0
        rows = []
        for stamp, frames in sorted(tf.items()):
            for _, _, q in frames.values():
                quat_error = max(quat_error, abs(sum(c * c for c in q) ** 0.5 - 1.0))
            if stamp in joints:
                position, _ = compose(frames, base, tool)
                rows.append({"stamp": stamp, "positions": joints[stamp], "tool": list(position)})
        out["rows"] = rows
        out["max_quaternion_norm_error"] = quat_error
        out["scene_entities"] = sorted(scene_ids)
        out["statuses_during_stream"] = statuses
        out["largest_message_bytes"] = sizes

        # The URDF through fetchAsset.
        await ws.send(json.dumps({"op": "fetchAsset", "uri": urdf_uri, "requestId": 77}))
        out["asset"] = await read_asset(ws, 77)
        await ws.send(json.dumps({"op": "fetchAsset", "uri": "package://nope/x.urdf", "requestId": 78}))
        out["missing_asset"] = await read_asset(ws, 78)

        # A client publish: refused with an error status.
        await ws.send(bytes([1]) + struct.pack("<I", 1) + b"\x00\x01")
        out["publish_reply"] = await next_text(ws)

    # An oversized message closes the connection with 1009.
    async with connect(url) as ws:
        await ws.recv()
        await ws.recv()
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [], "pad": "x" * 65536}))
        try:
            while True:
                await asyncio.wait_for(ws.recv(), 5)
        except websockets.ConnectionClosed as closed:
            out["oversized_close_code"] = closed.rcvd.code if closed.rcvd else None
        except asyncio.TimeoutError:
            out["oversized_close_code"] = "open"
    print(json.dumps(out))


async def read_asset(ws, request_id):
    while True:
        raw = await asyncio.wait_for(ws.recv(), 5)
        if isinstance(raw, bytes) and raw[0] == FETCH_ASSET_RESPONSE:
            rid, status, err_len = struct.unpack_from("<IBI", raw, 1)
            if rid != request_id:
                continue
            error = raw[10 : 10 + err_len].decode()
            data = raw[10 + err_len :]
            return {"status": status, "error": error, "bytes": len(data), "head": data[:64].decode(errors="replace")}


async def next_text(ws):
    while True:
        raw = await asyncio.wait_for(ws.recv(), 5)
        if isinstance(raw, str):
            return json.loads(raw)


if __name__ == "__main__":
    url, seconds, base, tool, urdf_uri = sys.argv[1:6]
    asyncio.run(run(url, float(seconds), base, tool, urdf_uri))
