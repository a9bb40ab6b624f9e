"""PyPI's `websockets` as a Foxglove ws-protocol client (subprotocol foxglove.websocket.v1,
https://github.com/foxglove/ws-protocol/blob/main/docs/spec.md) of `rigbridge serve`'s
`/program` topic: it takes the advertise, checks the channel is JSON with a JSON schema,
subscribes to it, and decodes every message (JSON text after the spec's 13-byte
messageData header: opcode 1, subscription id u32, receive timestamp u64, little-endian)
for a while; and `/scene`, decoded with the advertised protobuf schema (PyPI's
`protobuf`), for the parts' entities (`part-<name>`).

Usage: foxglove_program.py URL SECONDS
Prints one JSON object: the channel as advertised, the steps' texts in the order they
first came, the last message, and each part entity's positions as /scene moved it. Driven by tests/foxglove_live.rs.
"""
import asyncio
import base64
import json
import struct
import sys
import time

import websockets
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

SUBPROTOCOL = "foxglove.websocket.v1"
MESSAGE_DATA = 1


def message_class(channel):
    """The protobuf class of a channel, from its base64 FileDescriptorSet."""
    files = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
    pool = descriptor_pool.DescriptorPool()
    for file in files.file:
        pool.Add(file)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))


async def run(url, seconds):
    out = {"steps": [], "last": None, "messages": 0, "part_positions": {}}
    async with websockets.connect(url, subprotocols=[SUBPROTOCOL], max_size=2**24) as ws:
        await ws.recv()  # serverInfo
        advertise = json.loads(await ws.recv())
        channel = next(c for c in advertise["channels"] if c["topic"].endswith("/program"))
        out["channel"] = channel
        out["schema"] = json.loads(channel["schema"])
        scene = next(c for c in advertise["channels"] if c["topic"].endswith("/scene"))
        scene_class = message_class(scene)
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": 7, "channelId": channel["id"]}, {"id": 8, "channelId": scene["id"]}]}))
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            try:
                raw = await asyncio.wait_for(ws.recv(), deadline - time.monotonic())
            except asyncio.TimeoutError:
                break
            if isinstance(raw, str):
                continue
            assert raw[0] == MESSAGE_DATA, raw[0]
            sub_id, _ = struct.unpack_from("<IQ", raw, 1)
            if sub_id == 8:
                for entity in scene_class.FromString(raw[13:]).entities:
                    if entity.id.startswith("part-"):
                        p = entity.triangles[0].pose.position
                        seen = out["part_positions"].setdefault(entity.id, [])
                        if not seen or seen[-1] != [p.x, p.y, p.z]:
                            seen.append([p.x, p.y, p.z])
                continue
            assert sub_id == 7, sub_id
            message = json.loads(raw[13:].decode("utf-8"))
            out["messages"] += 1
            out["last"] = message
            step = message.get("step")
            if step and (not out["steps"] or out["steps"][-1] != step["text"]):
                out["steps"].append(step["text"])
    print(json.dumps(out))


if __name__ == "__main__":
    asyncio.run(run(sys.argv[1], float(sys.argv[2])))
