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
The connection, the schema decoding and the receive loop are foxglove_ws.py's.
"""
import asyncio
import json
import struct
import sys
import time

from foxglove_ws import MESSAGE_DATA, connect, message_class, received_until


async def run(url, seconds):
    out = {"steps": [], "last": None, "messages": 0, "part_positions": {}}
    async with connect(url) as ws:
        await ws.recv()  # serverInfo
        advertise = json.loads(await ws.recv())
        channel = next(c for c in advertise["channels"] if c["topic"].endswith("/program"))
        out["channel"] = channel
        out["schema"] = json.loads(channel["schema"])
        scene = next(c for c in advertise["channels"] if c["topic"].endswith("/scene"))
        scene_class = message_class(scene)
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": 7, "channelId": channel["id"]}, {"id": 8, "channelId": scene["id"]}]}))
        async for raw in received_until(ws, time.monotonic() + seconds):
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
