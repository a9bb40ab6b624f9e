"""PyPI's `websockets` as a Foxglove ws-protocol client (subprotocol foxglove.websocket.v1,
https://github.com/foxglove/ws-protocol/blob/main/docs/spec.md) of `rigbridge serve`'s
`/program` topic: it takes the advertise, checks the channel is JSON with a JSON schema,
subscribes to it, and decodes every message (JSON text after the spec's 13-byte
messageData header: opcode 1, subscription id u32, receive timestamp u64, little-endian)
for a while.

Usage: foxglove_program.py URL SECONDS
Prints one JSON object: the channel as advertised, the steps' texts in the order they
first came, and the last message. Driven by tests/foxglove_live.rs.
"""
import asyncio
import json
import struct
import sys
import time

import websockets

SUBPROTOCOL = "foxglove.websocket.v1"
MESSAGE_DATA = 1


async def run(url, seconds):
    out = {"steps": [], "last": None, "messages": 0}
    async with websockets.connect(url, subprotocols=[SUBPROTOCOL], max_size=2**24) as ws:
        await ws.recv()  # serverInfo
        advertise = json.loads(await ws.recv())
        channel = next(c for c in advertise["channels"] if c["topic"].endswith("/program"))
        out["channel"] = channel
        out["schema"] = json.loads(channel["schema"])
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": channel["id"]}]}))
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
