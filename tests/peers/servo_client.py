"""A servo client we did not write the WebSocket side of (PyPI's `websockets`), for
tests/servo.rs: it streams tool poses on a circle at its own rate to `GET /api/servo`,
stops, reads the commanded position from `GET /api/status` to see the arm at rest, sends
bad targets (a joint outside its limits, NaN, an unreachable pose, one sent before the
last) and reads the commanded position again, tries a second client while it is
connected, and a client while a planned job runs. It judges nothing: it prints what it saw as one JSON line on stdout.

Usage: servo_client.py HOST:PORT X Y Z QW QX QY QZ RADIUS_M SPEED_M_S RATE_HZ SECONDS
"""

import asyncio
import json
import math
import sys
import time
import urllib.request

from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus

# How long the status is read after the stream stops: the bridge's timeout (100 ms), the
# brake's ramp (tens of ms on the IRB 120 at these speeds) and the status' own latency.
REST_CHECK_AFTER_S = 0.3
# Two readings this far apart that agree: the arm is at rest.
REST_GAP_S = 0.1


def status(address):
    with urllib.request.urlopen(f"http://{address}/api/status", timeout=10) as answer:
        return json.load(answer)


def commanded(address):
    return [axis["value"] for axis in status(address)["commanded"]]


def post(address, path, body):
    request = urllib.request.Request(
        f"http://{address}{path}",
        data=json.dumps(body).encode(),
        headers={"Content-Type": "application/json"},
        method="POST",
    )
    with urllib.request.urlopen(request, timeout=10) as answer:
        return json.load(answer)


async def replies(socket, within):
    """Every message the server sends within `within` seconds."""
    seen = []
    deadline = time.monotonic() + within
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            return seen
        try:
            seen.append(json.loads(await asyncio.wait_for(socket.recv(), left)))
        except asyncio.TimeoutError:
            return seen


async def refusal(url):
    """The status and body a client is refused with, or None when it is let in."""
    try:
        async with connect(url):
            return None
    except InvalidStatus as refused:
        return {
            "status": refused.response.status_code,
            "body": refused.response.body.decode(errors="replace"),
        }


async def main():
    address = sys.argv[1]
    x, y, z, qw, qx, qy, qz, radius, speed, rate, seconds = map(float, sys.argv[2:13])
    url = f"ws://{address}/api/servo"
    result = {"sessions": [], "stream_errors": []}
    async with connect(url) as socket:
        period = 1.0 / rate
        start = time.monotonic()
        messages = int(seconds * rate)
        for m in range(messages):
            # On time: each message at its own instant of the client's clock.
            await asyncio.sleep(max(0.0, start + m * period - time.monotonic()))
            angle = speed / radius * (m * period)
            pose = {
                "xyz_m": [x, y + radius * (math.cos(angle) - 1.0), z + radius * math.sin(angle)],
                "quat_wxyz": [qw, qx, qy, qz],
            }
            # When it was sent, on the client's clock: the pose's own instant.
            await socket.send(json.dumps({"pose": pose, "sent_s": m / rate}))
            sent_at = time.monotonic()
            if m > 0:
                result["max_gap_s"] = max(result.get("max_gap_s", 0.0), sent_at - last_sent)
            last_sent = sent_at
        result["stream_s"] = time.monotonic() - start
        for reply in await replies(socket, REST_CHECK_AFTER_S):
            if "session" in reply:
                result["sessions"].append(reply["session"])
            else:
                result["stream_errors"].append(reply)
        first = commanded(address)
        await asyncio.sleep(REST_GAP_S)
        result["rest"] = [first, commanded(address)]
        bad = [
            {"joints_deg": [0.0, 0.0, 80.0, 0.0, 30.0, 0.0]},
            # Python's json writes NaN as the bare word, which JSON does not allow.
            '{"joints_deg": [NaN, 0.0, 0.0, 0.0, 30.0, 0.0]}',
            {"joints_deg": [0.0, 0.0, 0.0, 0.0, 30.0]},
            {"pose": {"xyz_m": [2.0, 0.0, 0.5], "quat_wxyz": [qw, qx, qy, qz]}},
            {
                "joints_deg": [10.0, 0.0, 0.0, 0.0, 30.0, 0.0],
                "pose": {"xyz_m": [x, y, z], "quat_wxyz": [qw, qx, qy, qz]},
            },
            # Sent (by its own word) before the stream's last target.
            {"joints_deg": [0.0, 0.0, 0.0, 0.0, 30.0, 0.0], "sent_s": 0.0},
        ]
        result["bad"] = []
        for message in bad:
            text = message if isinstance(message, str) else json.dumps(message)
            await socket.send(text)
            result["bad"].append({"sent": text, "replies": await replies(socket, 0.2)})
        result["after_bad"] = commanded(address)
        result["second_client"] = await refusal(url)
    # The online session holds for 5 s with nothing to do: stop it, then start a job.
    post(address, "/api/stop", {})
    deadline = time.monotonic() + 10.0
    while status(address)["state"] != "idle" and time.monotonic() < deadline:
        await asyncio.sleep(0.05)
    result["job"] = post(
        address,
        "/api/jobs",
        {"job": {"kind": "move_joints", "targets_deg": [[10.0, 0.0, 0.0, 0.0, 30.0, 0.0]]}},
    )
    result["during_job"] = await refusal(url)
    print(json.dumps(result))


asyncio.run(main())
