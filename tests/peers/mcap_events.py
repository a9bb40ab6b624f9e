"""Reads a rigbridge MCAP log with a reader we did not write: PyPI's `mcap` (Foxglove's
reference implementation). Prints one JSON line per message on `/rigbridge/events`: its
log time in nanoseconds, and the event's `t`, `kind` and `detail` as decoded from the JSON
message. Driven by tests/serve_jobs.rs; scripts/test.sh installs the package in a venv.
"""
import json
import sys

from mcap.reader import make_reader

with open(sys.argv[1], "rb") as f:
    for schema, channel, message in make_reader(f).iter_messages(topics=["/rigbridge/events"]):
        event = json.loads(message.data)
        print(json.dumps({
            "log_time": message.log_time,
            "encoding": channel.message_encoding,
            "t": event["t"],
            "kind": event["kind"],
            "detail": event.get("detail"),
        }))
