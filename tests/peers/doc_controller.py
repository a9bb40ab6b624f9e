#!/usr/bin/env python3
"""A strict robot controller for the rigbridge wire protocol, version 3 (or 2).

Written from docs/protocol.md alone (no look at the bridge's code), as an independent
vendor would: a TCP server that speaks COBS/CRC-32 framing, answers the bridge's Hello,
checks every Target on the wire integers (6.6), latches faults, runs a watchdog and a
simple servo model on its own 4 ms clock, and writes a JSON summary when the bridge
disconnects or on SIGTERM.

Version 3 (the default; 3.6, 6.10): its Hellos carry version byte 3, it takes types
0x01-0x08 with version byte 2 or 3, keeps named digital outputs (some of them actuators,
answered when they have finished moving) and inputs (scriptable with --input), and answers
every SetOutput and ReadInput with one IoState. `--version 2` makes it a version 2
controller exactly (Hellos with version byte 2, version 3 frames counted as
unsupported_version, no I/O). What it received is in the summary: `outputs_set` (every
SetOutput in order, with its value and result), `outputs_done` ([name, value] of those
carried out, in order) and `inputs_read`. The ambiguities met while writing version 3 from
the doc are listed in AMBIGUITIES.md (the docctl branch).

Python 3.11, standard library only. The first stdout line is the TCP port it listens on;
events go to stderr.

Section numbers in comments refer to docs/protocol.md.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import selectors
import signal
import socket
import struct
import sys
import time
import tomllib
import zlib

VERSION = 2  # the version byte of types 0x01-0x08 (2, whatever the session's version)
IO_VERSION = 3  # the version byte of the I/O types 0x09-0x0B (2.)
MAX_AXES = 32
MAX_BODY_LEN = 1600
MAX_COBS_LEN = 1607  # MAX_FRAME_LEN less the delimiter (2.3)
T_LIMIT = 1 << 48

HELLO, TARGET, STOP, ESTOP, HEARTBEAT, FEEDBACK, FAULT, RESET = range(1, 9)
SET_OUTPUT, READ_INPUT, IO_STATE = 0x09, 0x0A, 0x0B  # version 3 (3.6)
IO_TYPES = (SET_OUTPUT, READ_INPUT, IO_STATE)
KIND_OUTPUT, KIND_INPUT = 0, 1
R_DONE, R_NO_SUCH, R_REFUSED = 0, 1, 2
TYPE_NAMES = {
    HELLO: "hello",
    TARGET: "target",
    STOP: "stop",
    ESTOP: "estop",
    HEARTBEAT: "heartbeat",
    FEEDBACK: "feedback",
    FAULT: "fault",
    RESET: "reset",
    SET_OUTPUT: "set_output",
    READ_INPUT: "read_input",
    IO_STATE: "io_state",
}

ST_OK, ST_HOLDING, ST_FAULT = 0, 1, 2
F_LIMITS, F_SPEED, F_AXES, F_ESTOP, F_ACCEL, F_BUSY = 1, 2, 3, 4, 5, 6

I32_MIN, I32_MAX = -(1 << 31), (1 << 31) - 1


def log(msg: str) -> None:
    sys.stderr.write(f"[doc_controller {time.monotonic():.3f}] {msg}\n")
    sys.stderr.flush()


def now_us() -> int:
    return time.monotonic_ns() // 1000


def round_half_away(x: float) -> int:
    """1. Conventions: rounded to nearest, half away from zero."""
    if not math.isfinite(x):
        raise ValueError(f"not finite: {x}")
    r = math.floor(abs(x) + 0.5)
    return int(r if x >= 0 else -r)


def to_micro_i32(x: float) -> int:
    v = round_half_away(x * 1e6)
    if not I32_MIN <= v <= I32_MAX:
        raise ValueError(f"out of range for i32: {x}")
    return v


def deg_to_urad(deg: float) -> int:
    return to_micro_i32(deg * (math.pi / 180.0))


def ceil_div(num: int, den: int) -> int:
    """Exact ceil(num / den) for integers, den > 0."""
    return -((-num) // den)


# --------------------------------------------------------------------------------------
# 2.1 CRC-32 and 2.2 COBS


def crc32(data: bytes) -> int:
    return zlib.crc32(data) & 0xFFFFFFFF


def cobs_encode(body: bytes) -> bytes:
    """2.2: blocks split at each 0x00, code len + 1; a 254-byte block gets code 0xFF
    (no zero implied), and no block is started after a trailing 0xFF block."""
    out = bytearray()
    block = bytearray()
    last_was_ff = False
    for b in body:
        if b == 0:
            out.append(len(block) + 1)
            out += block
            block.clear()
            last_was_ff = False
        else:
            block.append(b)
            last_was_ff = False
            if len(block) == 254:
                out.append(0xFF)
                out += block
                block.clear()
                last_was_ff = True
    if not last_was_ff:
        out.append(len(block) + 1)
        out += block
    return bytes(out)


def cobs_decode(data: bytes) -> bytes | None:
    out = bytearray()
    i = 0
    n = len(data)
    while i < n:
        c = data[i]
        if c == 0:
            return None
        i += 1
        if i + c - 1 > n:
            return None
        out += data[i : i + c - 1]
        i += c - 1
        if c < 0xFF and i < n:
            out.append(0)
    return bytes(out)


def body_of(msg_type: int, payload: bytes, version: int | None = None) -> bytes:
    """2.: version | type | payload | crc. The version byte is the one that defined the
    layout (2 for 0x01-0x08, 3 for 0x09-0x0B) unless given (a v3 controller's Hello: 3)."""
    if version is None:
        version = IO_VERSION if msg_type in IO_TYPES else VERSION
    body = bytes([version, msg_type]) + payload
    return body + struct.pack("<I", crc32(body))


def frame(msg_type: int, payload: bytes, version: int | None = None) -> bytes:
    return cobs_encode(body_of(msg_type, payload, version)) + b"\x00"


def can_segments(base: int, offset: int, body: bytes, fd: bool = False) -> list[tuple[int, bytes]]:
    """7.4: a body cut into segments on one identifier: index u8, segment 0 with the
    body's length (u16), 5 body bytes in segment 0 and 7 in the others on classic CAN (61
    and 63 on FD, the last frame padded). The last classic frame carries what remains."""
    first, later = (61, 63) if fd else (5, 7)
    out = [(base + offset, bytes([0]) + struct.pack("<H", len(body)) + body[:first])]
    i, k = first, 1
    while i < len(body):
        out.append((base + offset, bytes([k]) + body[i : i + later]))
        i += later
        k += 1
    if fd:
        sizes = (8, 12, 16, 20, 24, 32, 48, 64)
        out = [(cid, d + bytes(next(n for n in sizes if n >= len(d)) - len(d))) for cid, d in out]
    return out


# 3.6: a name is 1 to 32 bytes, each an ASCII letter, digit or `_`.
NAME_BYTES = frozenset(b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789_")


def valid_io_name(name: str) -> bool:
    try:
        b = name.encode("ascii")
    except UnicodeEncodeError:
        return False
    return 1 <= len(b) <= 32 and all(c in NAME_BYTES for c in b)


def io_name_bytes(name: str) -> bytes:
    b = name.encode("ascii")
    return bytes([len(b)]) + b


def set_output_payload(request: int, value: int, name: str) -> bytes:
    return struct.pack("<IB", request, value) + io_name_bytes(name)


def read_input_payload(request: int, name: str) -> bytes:
    return struct.pack("<I", request) + io_name_bytes(name)


def io_state_payload(request: int, kind: int, result: int, value: int, name: str) -> bytes:
    return struct.pack("<IBBB", request, kind, result, value) + io_name_bytes(name)


# --------------------------------------------------------------------------------------
# 3. Messages: strict decoding of every type


class Malformed(Exception):
    pass


def decode_payload(msg_type: int, p: bytes) -> dict:
    if msg_type == HELLO:
        if len(p) < 1:
            raise Malformed("hello: empty")
        n = p[0]
        if n > MAX_AXES:
            raise Malformed(f"hello: {n} axes")
        i = 1
        names = []
        for _ in range(n):
            if i >= len(p):
                raise Malformed("hello: names cut")
            ln = p[i]
            i += 1
            if ln > 32 or i + ln > len(p):
                raise Malformed("hello: name length")
            try:
                names.append(p[i : i + ln].decode("utf-8"))
            except UnicodeDecodeError as e:
                raise Malformed("hello: name not UTF-8") from e
            i += ln
        if len(p) != i + 16 * n + 9:
            raise Malformed("hello: length")
        limits = [struct.unpack_from("<iiii", p, i + 16 * k) for k in range(n)]
        i += 16 * n
        cycle, watchdog, flags = struct.unpack_from("<IIB", p, i)
        if flags & ~1:
            raise Malformed("hello: unused flag bits")
        return {
            "names": names,
            "lower": [x[0] for x in limits],
            "upper": [x[1] for x in limits],
            "vmax": [x[2] for x in limits],
            "amax": [x[3] for x in limits],
            "cycle_us": cycle,
            "watchdog": watchdog,
            "answer": bool(flags & 1),
        }
    if msg_type == TARGET:
        if len(p) < 13:
            raise Malformed("target: short")
        seq, t, n = struct.unpack_from("<IQB", p, 0)
        if n > MAX_AXES or len(p) != 13 + 8 * n:
            raise Malformed("target: length")
        if t >= T_LIMIT:
            raise Malformed("target: t >= 2^48")
        pos = list(struct.unpack_from(f"<{n}i", p, 13))
        vel = list(struct.unpack_from(f"<{n}i", p, 13 + 4 * n))
        return {"seq": seq, "t": t, "pos": pos, "vel": vel}
    if msg_type in (STOP, ESTOP, HEARTBEAT, RESET):
        if p:
            raise Malformed("payload on an empty message")
        return {}
    if msg_type == FEEDBACK:
        if len(p) < 9:
            raise Malformed("feedback: short")
        seq, status, code, a, b, n = struct.unpack_from("<IBBBBB", p, 0)
        if n > MAX_AXES or len(p) != 9 + 4 * n:
            raise Malformed("feedback: length")
        check_fault_bytes(code, a, b, in_feedback=True, status=status)
        return {"seq": seq, "status": status, "code": code, "a": a, "b": b}
    if msg_type == FAULT:
        if len(p) < 4:
            raise Malformed("fault: short")
        code, a, b, ln = p[0], p[1], p[2], p[3]
        if ln > 128 or len(p) != 4 + ln:
            raise Malformed("fault: length")
        if code == 0:
            raise Malformed("fault: code 0")
        check_fault_bytes(code, a, b, in_feedback=False, status=ST_FAULT)
        try:
            text = p[4:].decode("utf-8")
        except UnicodeDecodeError as e:
            raise Malformed("fault: text not UTF-8") from e
        return {"code": code, "a": a, "b": b, "text": text}
    if msg_type in IO_TYPES:
        # Only reached for a version 3 frame at a version 3 receiver (2.3 check 4).
        fixed = {SET_OUTPUT: 5, READ_INPUT: 4, IO_STATE: 7}[msg_type]
        if len(p) < fixed + 1:
            raise Malformed(f"{TYPE_NAMES[msg_type]}: short")
        (request,) = struct.unpack_from("<I", p, 0)
        if request == 0:
            # 3.6: "A request of 0 ... makes the frame malformed" (read as applying to all
            # three I/O messages: AMBIGUITIES.md).
            raise Malformed(f"{TYPE_NAMES[msg_type]}: request 0")
        name = decode_io_name(p, fixed, msg_type)
        m = {"request": request, "name": name}
        if msg_type == SET_OUTPUT:
            if p[4] > 1:
                raise Malformed("set_output: value")
            m["value"] = p[4]
        elif msg_type == IO_STATE:
            kind, result, value = p[4], p[5], p[6]
            if kind > 1:
                raise Malformed("io_state: kind")
            if result > 2:
                raise Malformed("io_state: result")
            if value > 1:
                raise Malformed("io_state: value")
            m.update(kind=kind, result=result, value=value)
        return m
    raise Malformed(f"reserved type 0x{msg_type:02x}")


def decode_io_name(p: bytes, i: int, msg_type: int) -> str:
    """3.6: u8 length 1..32, then that many bytes, each an ASCII letter, digit or `_`;
    the name ends the payload (a byte too many or too few is malformed, 2.3)."""
    ln = p[i]
    if not 1 <= ln <= 32:
        raise Malformed(f"{TYPE_NAMES[msg_type]}: name length {ln}")
    if len(p) != i + 1 + ln:
        raise Malformed(f"{TYPE_NAMES[msg_type]}: length")
    raw = p[i + 1 :]
    if any(c not in NAME_BYTES for c in raw):
        raise Malformed(f"{TYPE_NAMES[msg_type]}: name byte")
    return raw.decode("ascii")


def check_fault_bytes(code: int, a: int, b: int, in_feedback: bool, status: int) -> None:
    if in_feedback:
        if status > 2:
            raise Malformed("status")
        if status != ST_FAULT:
            if code or a or b:
                raise Malformed("fault bytes without a fault")
            return
        if code == F_BUSY or code == 0:
            raise Malformed("feedback fault code")
    if code in (F_LIMITS, F_SPEED, F_ACCEL):
        if b:
            raise Malformed("fault b")
    elif code == F_AXES:
        pass
    elif code in (F_ESTOP, F_BUSY):
        if a or b:
            raise Malformed("fault a/b")
    else:
        raise Malformed(f"fault code {code}")


class Decoder:
    """2.3 Receiving, with the bridge's counters. `version`: the receiver's, 2 or 3."""

    def __init__(self, version: int = 3) -> None:
        self.version = version
        self.buf = bytearray()
        self.skipping = False  # dropping an over-long frame until the next delimiter
        self.c = {
            "frames": 0,
            "crc_errors": 0,
            "unsupported_version": 0,
            "malformed": 0,
            "oversized": 0,
            "overruns": 0,
            "bytes_discarded": 0,
        }
        self.malformed_reasons: dict[str, int] = {}

    def reset(self) -> None:
        if self.buf:
            self.c["bytes_discarded"] += len(self.buf)
        self.buf.clear()
        self.skipping = False

    def push(self, data: bytes) -> list[tuple[int, dict]]:
        out = []
        for b in data:
            if b == 0:
                if self.skipping:
                    self.skipping = False
                    continue
                if not self.buf:
                    continue  # empty frame: counted nowhere
                raw = bytes(self.buf)
                self.buf.clear()
                m = self._frame(raw)
                if m is not None:
                    out.append(m)
                continue
            if self.skipping:
                self.c["bytes_discarded"] += 1
                continue
            self.buf.append(b)
            if len(self.buf) > MAX_COBS_LEN:
                self.c["oversized"] += 1
                self.c["bytes_discarded"] += len(self.buf)
                self.buf.clear()
                self.skipping = True
        return out

    def _bad(self, counter: str, raw: bytes, reason: str = "") -> None:
        self.c[counter] += 1
        self.c["bytes_discarded"] += len(raw)
        if reason:
            self.malformed_reasons[reason] = self.malformed_reasons.get(reason, 0) + 1

    def _frame(self, raw: bytes) -> tuple[int, dict] | None:
        body = cobs_decode(raw)
        if body is None:
            self._bad("malformed", raw, "cobs")
            return None
        if len(body) < 6 or len(body) > MAX_BODY_LEN:
            self._bad("oversized", raw)
            return None
        (crc,) = struct.unpack_from("<I", body, len(body) - 4)
        if crc != crc32(body[:-4]):
            self._bad("crc_errors", raw)
            return None
        # 3. the version: 2 or 3 at a version 3 receiver, 2 only at a version 2 one.
        if body[0] not in ((2, 3) if self.version == 3 else (2,)):
            self._bad("unsupported_version", raw)
            return None
        # 4. types 0x01-0x08 with version byte 2 or 3; 0x09-0x0B with version byte 3 only
        # (an I/O type in a version 2 frame is malformed). A version 2 receiver never gets
        # here with version byte 3, and takes 0x09-0x0B as reserved (malformed).
        if body[1] in IO_TYPES and body[0] != IO_VERSION:
            self._bad("malformed", raw, f"{TYPE_NAMES[body[1]]} in a version {body[0]} frame")
            return None
        try:
            fields = decode_payload(body[1], body[2:-4])
        except Malformed as e:
            self._bad("malformed", raw, str(e))
            return None
        fields["_version"] = body[0]
        self.c["frames"] += 1
        return body[1], fields


# --------------------------------------------------------------------------------------
# Configuration


class Axis:
    def __init__(self, name, lower, upper, vmax, amax, initial):
        self.name = name
        self.lower = lower
        self.upper = upper
        self.vmax = vmax
        self.amax = amax
        self.initial = initial


def axis_index(axes: list[Axis], key: str) -> int:
    for k, a in enumerate(axes):
        if a.name == key:
            return k
    try:
        k = int(key) - 1
    except ValueError:
        sys.exit(f"doc_controller: no axis {key!r}")
    if not 0 <= k < len(axes):
        sys.exit(f"doc_controller: axis {key!r} out of range 1..{len(axes)}")
    return k


def load_axes(args) -> list[Axis]:
    with open(args.rig, "rb") as f:
        rig = tomllib.load(f)
    initial = [float(x) for x in args.initial_deg.split(",")] if args.initial_deg else []
    axes = []
    for k, j in enumerate(rig["joint"]):
        init = initial[k] if k < len(initial) else 0.0
        if j.get("kind", "revolute") == "prismatic":
            axes.append(
                Axis(
                    j["name"],
                    to_micro_i32(j["lower_m"]),
                    to_micro_i32(j["upper_m"]),
                    to_micro_i32(j["max_speed_m_s"]),
                    to_micro_i32(j["max_accel_m_s2"]),
                    to_micro_i32(init),
                )
            )
        else:
            axes.append(
                Axis(
                    j["name"],
                    deg_to_urad(j["lower_deg"]),
                    deg_to_urad(j["upper_deg"]),
                    deg_to_urad(j["max_speed_deg_s"]),
                    deg_to_urad(j["max_accel_deg_s2"]),
                    deg_to_urad(init),
                )
            )
    # Overrides, applied in a fixed order; each makes the controller differ from the rig.
    for key, f in args.limit_scale_axis:
        a = axes[axis_index(axes, key)]
        a.lower = round_half_away(a.lower * float(f))
        a.upper = round_half_away(a.upper * float(f))
    for key, v in args.lower_deg:
        axes[axis_index(axes, key)].lower = deg_to_urad(float(v))
    for key, v in args.upper_deg:
        axes[axis_index(axes, key)].upper = deg_to_urad(float(v))
    for key, v in args.speed_deg_s:
        axes[axis_index(axes, key)].vmax = deg_to_urad(float(v))
    for key, v in args.accel_deg_s2:
        axes[axis_index(axes, key)].amax = deg_to_urad(float(v))
    for field, key, v in args.set_urad:
        if field not in ("lower", "upper", "vmax", "amax"):
            sys.exit(f"doc_controller: --set-urad field {field!r}")
        setattr(axes[axis_index(axes, key)], field, int(v))
    for key, name in args.rename:
        axes[axis_index(axes, key)].name = name
    if args.axes is not None:
        while len(axes) > args.axes:
            axes.pop()
        while len(axes) < args.axes:
            k = len(axes) + 1
            axes.append(
                Axis(
                    f"joint_{k}",
                    deg_to_urad(-180),
                    deg_to_urad(180),
                    deg_to_urad(250),
                    deg_to_urad(1000),
                    0,
                )
            )
    if not axes or len(axes) > MAX_AXES:
        sys.exit(f"doc_controller: {len(axes)} axes")
    for a in axes:
        a.initial = min(max(a.initial, a.lower), a.upper)
    return axes


# --------------------------------------------------------------------------------------
# The controller


class Conn:
    def __init__(self, sock: socket.socket, peer) -> None:
        self.sock = sock
        self.peer = peer
        self.out = bytearray()
        self.hello_sent = False  # from its first Hello on, Feedback every cycle (6.1.3)
        self.answer_sent = False
        self.answer_then_feedback = False  # answer Hello and one Feedback after it sent
        self.last_valid_us = now_us()
        self.silence_lost = False


class Controller:
    def __init__(self, args, axes: list[Axis]) -> None:
        self.args = args
        self.axes = axes
        self.n = len(axes)
        self.T = args.cycle_us
        self.w = args.watchdog
        self.delay_us = args.delay_cycles * self.T
        self.alpha = 1.0 - math.exp(-2.0 * math.pi * args.bandwidth_hz * self.T / 1e6)
        self.offsets = [0.0] * self.n
        if args.hold_axis_offset_deg:
            key, deg = args.hold_axis_offset_deg
            self.offsets[axis_index(axes, key)] = deg * math.pi / 180.0 * 1e6
        # servo state (floats, µrad)
        self.actual = [float(a.initial) for a in axes]
        self.setpoint = [float(a.initial) for a in axes]
        self.sp_vel = [0.0] * self.n  # µrad per cycle, of the setpoint
        self.decelerating = False
        self.queue: list[tuple[int, list[int]]] = []  # (apply at, positions)
        # protocol state
        self.status = ST_HOLDING
        self.fault = (0, 0, 0)
        self.bound = False
        self.have_last = False  # sequence tracking (6.3)
        self.last_seq = 0
        self.echo = 0
        self.ref = [round(x) for x in self.setpoint]
        self.vref = [0] * self.n
        self.ref_prev = list(self.ref)
        self.ref_second_ok = True  # ref accepted with d = 1 after ref_prev, or held
        self.last_t = None
        self.t_offset = None  # arrival - t, aligned at the first target after a Hello
        self.accepted_since_tick = False
        self.wd_count = 0
        self.ever_accepted = False
        self.started_hello_pending = args.unprompted_hello != "never"
        self.conn: Conn | None = None
        self.version = args.version  # 6.10: the version byte of every Hello of ours
        self.decoder = Decoder(self.version)
        # 3.6 / 6.10: named digital outputs and inputs; a controller's restart starts with
        # every output 0 (6.10 rule 7).
        self.outputs: dict[str, int] = {n: 0 for n in args.output_names}
        self.actuators: dict[str, float] = dict(args.actuator_s)  # seconds to finish moving
        self.inputs: dict[str, int] = {n: 0 for n in args.input_names}
        self.input_script = list(args.input_script)  # fired once each, in order
        for name, value in args.input_initial:
            self.inputs[name] = value
        self.moving_until: dict[str, int] = {}  # actuator -> µs when it finishes moving
        self.pending: dict[str, dict] = {}  # output -> the SetOutput answered when done
        self.output_set_at: dict[tuple[str, int], int] = {}  # (output, value) -> first µs
        self.first_target_us: int | None = None
        self.io_next_request = 1
        self.sessions_started = 0
        self.sessions_ended = 0
        self.stop_requested = False
        self.tick_no = 0
        self.local_reset_done = False
        self.s = {
            "targets_received": 0,
            "targets_received_bound": 0,
            "targets_before_answer": 0,
            "accepted": 0,
            "dropped_unbound": 0,
            "dropped_duplicate": 0,
            "dropped_older": 0,
            "dropped_faulted": 0,
            "dropped_ignored": 0,
            "lost_in_gaps": 0,
            "gaps": 0,
            "late_targets": 0,
            "late_past_apply_time": 0,
            "max_lateness_us": 0,
            "t_irregular": 0,
            "max_t_error_us": 0,
            "refused": [],
            "bridge_hellos": 0,
            "bridge_hellos_malformed_or_answer": 0,
            "answers_sent": 0,
            "unprompted_hellos_sent": 0,
            "stops": 0,
            "estops": 0,
            "resets": 0,
            "resets_ignored": 0,
            "heartbeats": 0,
            "wrong_side_messages": 0,
            "watchdog_holds": 0,
            "local_resets": 0,
            "link_losses_transport": 0,
            "link_losses_silence": 0,
            "busy_refusals": 0,
            "feedback_sent": 0,
            "max_rx_gap_us": 0,
            "ticks": 0,
            "late_ticks": 0,
            "max_tick_lateness_us": 0,
            "first_accepted_seq": None,
            "last_accepted_seq": None,
            "last_bridge_hello": None,
            # version 3 (3.6, 6.10)
            "protocol_version": args.version,
            "bridge_hellos_v3": 0,
            "set_outputs_received": 0,
            "read_inputs_received": 0,
            "io_states_received": 0,
            "io_states_sent": 0,
            "io_results": {"done": 0, "no_such": 0, "refused": 0},
            "io_refusals": {},
            "io_request_irregular": 0,
            "io_overlapping": 0,
            "io_answers_dropped_link_loss": 0,
            "max_io_answer_delay_us": 0,
            # Every SetOutput in arrival order: session, request, name, value, result
            # (None until answered), answer_delay_ms.
            "outputs_set": [],
            # [name, value] of every SetOutput carried out (result 0), in arrival order.
            "outputs_done": [],
            # ReadInputs, consecutive equal ones merged: name, value, result, count.
            "inputs_read": [],
            "input_changes": [],
        }
        self.per_axis = [
            {
                "name": a.name,
                "lower": a.lower,
                "upper": a.upper,
                "vmax": a.vmax,
                "amax": a.amax,
                "step_limit_d1": ceil_div(a.vmax * self.T, 10**6) + 1,
                "vel_change_limit_d1": ceil_div(a.amax * self.T, 10**6) + 1,
                "second_diff_limit": ceil_div(a.amax * self.T * self.T, 10**12) + 2,
                "max_step": 0,
                "max_step_excess": None,  # max over accepted of |step| - allowance(d)
                "max_vel_change": 0,
                "max_vel_change_excess": None,
                "max_second_diff": 0,
                "second_diff_checked": 0,
                "max_abs_velocity": 0,
                "min_position": None,
                "max_position": None,
                "max_following_error": 0.0,
            }
            for a in axes
        ]

    # ---------------------------------------------------------------- sending

    def send(self, data: bytes) -> None:
        if self.conn is not None:
            self.conn.out += data

    def hello_payload(self, answer: bool) -> bytes:
        p = bytearray([self.n])
        for a in self.axes:
            nb = a.name.encode("utf-8")
            p.append(len(nb))
            p += nb
        for a in self.axes:
            p += struct.pack("<iiii", a.lower, a.upper, a.vmax, a.amax)
        p += struct.pack("<IIB", self.T, self.w, 1 if answer else 0)
        return bytes(p)

    def send_hello(self, answer: bool) -> None:
        if self.conn is None:
            return
        # 6.10: every Hello of ours (answers and unprompted ones) carries our version.
        self.send(frame(HELLO, self.hello_payload(answer), version=self.version))
        self.conn.hello_sent = True
        if answer:
            self.conn.answer_sent = True
            self.s["answers_sent"] += 1
        else:
            self.s["unprompted_hellos_sent"] += 1
        log(f"sent hello answer={answer}")

    def send_fault(self, code: int, a: int, b: int, text: str) -> None:
        tb = text.encode("utf-8")[:128]
        self.send(frame(FAULT, bytes([code, a, b, len(tb)]) + tb))

    def offset_on(self) -> bool:
        return self.ever_accepted and self.s["accepted"] >= self.args.offset_after

    def send_feedback(self) -> None:
        code, a, b = self.fault if self.status == ST_FAULT else (0, 0, 0)
        measured = [
            round_half_away(self.actual[k] + (self.offsets[k] if self.offset_on() else 0.0))
            for k in range(self.n)
        ]
        p = struct.pack("<IBBBBB", self.echo, self.status, code, a, b, self.n)
        p += struct.pack(f"<{self.n}i", *measured)
        self.send(frame(FEEDBACK, p))
        self.s["feedback_sent"] += 1
        if self.conn is not None and self.conn.answer_sent:
            self.conn.answer_then_feedback = True

    # ---------------------------------------------------------------- state changes

    def start_hold(self, why: str) -> None:
        """6.5 Holding: discard the queue, decelerate within amax, status 1."""
        self.queue.clear()
        if self.status != ST_FAULT:
            self.status = ST_HOLDING
        self.decelerating = True
        self.set_ref_held()
        log(f"hold ({why})")

    def set_ref_held(self) -> None:
        rest = self.rest_position()
        self.ref = [round_half_away(x) for x in rest]
        self.vref = [0] * self.n
        self.ref_prev = list(self.ref)
        self.ref_second_ok = True

    def rest_position(self) -> list[float]:
        """Where the setpoint comes to rest decelerating at amax from sp_vel."""
        out = []
        for k, a in enumerate(self.axes):
            v = self.sp_vel[k]  # µrad per cycle
            dv = a.amax * self.T * self.T / 1e12  # µrad per cycle per cycle
            x = self.setpoint[k]
            while abs(v) > 1e-9:
                v = v - math.copysign(min(abs(v), dv), v)
                x += v
            out.append(min(max(x, a.lower), a.upper))
        return out

    def latch_fault(self, code: int, a: int, b: int, text: str) -> None:
        self.queue.clear()
        self.status = ST_FAULT
        self.fault = (code, a, b)
        self.decelerating = True
        self.set_ref_held()
        self.send_fault(code, a, b, text)
        log(f"fault latched: code {code} a {a} b {b}: {text}")

    def become_unbound(self) -> None:
        self.bound = False

    def link_loss(self, why: str) -> None:
        if why == "silence":
            self.s["link_losses_silence"] += 1
        else:
            self.s["link_losses_transport"] += 1
        if self.status == ST_OK:
            self.start_hold("link loss: " + why)
        else:
            self.queue.clear()
        self.decoder.reset()
        self.become_unbound()
        # 6.10: outputs keep their values (an actuator keeps moving), but the answers owed
        # to the session that ended are not sent into the next one (AMBIGUITIES.md).
        if self.pending:
            self.s["io_answers_dropped_link_loss"] += len(self.pending)
            for pend in self.pending.values():
                pend["entry"]["result"] = "dropped_link_loss"
            self.pending.clear()
        self.io_next_request = 1
        log(f"link loss ({why})")

    # ---------------------------------------------------------------- receiving

    def on_message(self, mtype: int, m: dict, arrival: int) -> None:
        c = self.conn
        if c is not None:
            gap = arrival - c.last_valid_us
            self.s["max_rx_gap_us"] = max(self.s["max_rx_gap_us"], gap)
            c.last_valid_us = arrival
            c.silence_lost = False
        if mtype == HELLO:
            if m["answer"]:
                # 3.1: bit 0 set by the bridge is malformed; never answer it (6.1.2).
                self.s["bridge_hellos_malformed_or_answer"] += 1
                self.decoder.c["frames"] -= 1
                self.decoder.c["malformed"] += 1
                return
            self.on_bridge_hello(m)
        elif mtype == TARGET:
            self.on_target(m, arrival)
        elif mtype == STOP:
            self.s["stops"] += 1
            log(f"stop (echo {self.echo})")
            if self.status == ST_OK:
                self.start_hold("stop")
            elif self.status == ST_HOLDING:
                self.queue.clear()
        elif mtype == ESTOP:
            self.s["estops"] += 1
            self.queue.clear()
            self.setpoint = list(self.actual)
            self.sp_vel = [0.0] * self.n
            self.decelerating = False
            if self.status != ST_FAULT or self.fault[0] != F_ESTOP:
                self.status = ST_FAULT
                self.fault = (F_ESTOP, 0, 0)
                self.set_ref_held()
                self.send_fault(F_ESTOP, 0, 0, "e-stop")
                log("e-stop latched")
        elif mtype == HEARTBEAT:
            self.s["heartbeats"] += 1
        elif mtype == RESET:
            self.s["resets"] += 1
            if self.status != ST_FAULT:
                self.s["resets_ignored"] += 1
                return
            if self.args.refuse_reset:
                code, a, b = self.fault
                self.send_fault(code, a, b, "reset only from the pendant")
                return
            # 6.7: setpoint where the arm stands, holding, unbound, unprompted Hello.
            self.setpoint = list(self.actual)
            self.sp_vel = [0.0] * self.n
            self.decelerating = False
            self.status = ST_HOLDING
            self.fault = (0, 0, 0)
            self.set_ref_held()
            self.become_unbound()
            self.send_hello(answer=False)
            log("fault reset")
        elif mtype == SET_OUTPUT:
            self.on_set_output(m, arrival)
        elif mtype == READ_INPUT:
            self.on_read_input(m, arrival)
        elif mtype == IO_STATE:
            # From the controller's side only: ignored (3.).
            self.s["io_states_received"] += 1
            self.s["wrong_side_messages"] += 1
        else:
            # Feedback or Fault from the bridge: wrong side, ignored (3.).
            self.s["wrong_side_messages"] += 1

    # ---------------------------------------------------------------- I/O (version 3)

    def io_request_arrived(self, m: dict) -> None:
        """6.10 rule 1, as the controller sees it: counted, never refused for."""
        if m["request"] != self.io_next_request:
            self.s["io_request_irregular"] += 1
            log(f"I/O request {m['request']}, expected {self.io_next_request}")
        self.io_next_request = (m["request"] + 1) % (1 << 32) or 1
        if self.pending:
            self.s["io_overlapping"] += 1

    def send_io_state(self, request: int, kind: int, result: int, value: int, name: str,
                      arrival: int) -> None:
        """6.10 rule 2: one IoState per request, same number, kind and name."""
        if result != R_DONE:
            value = 0  # 3.6: 0 when result is not 0
        self.send(frame(IO_STATE, io_state_payload(request, kind, result, value, name)))
        self.s["io_states_sent"] += 1
        self.s["io_results"][("done", "no_such", "refused")[result]] += 1
        delay = now_us() - arrival
        self.s["max_io_answer_delay_us"] = max(self.s["max_io_answer_delay_us"], delay)

    def refuse_io(self, why: str) -> None:
        self.s["io_refusals"][why] = self.s["io_refusals"].get(why, 0) + 1

    def on_set_output(self, m: dict, arrival: int) -> None:
        s = self.s
        s["set_outputs_received"] += 1
        self.io_request_arrived(m)
        name, value, request = m["name"], m["value"], m["request"]
        entry = {
            "session": self.sessions_started,
            "request": request,
            "name": name,
            "value": value,
            "result": None,
            "answer_delay_ms": None,
        }
        s["outputs_set"].append(entry)

        def answer(result: int) -> None:
            entry["result"] = result
            entry["answer_delay_ms"] = round((now_us() - arrival) / 1000, 3)
            self.send_io_state(request, KIND_OUTPUT, result, value, name, arrival)

        # Rule 6 before rule 5 (AMBIGUITIES.md): a name we do not have, of this kind, is
        # result 1 whatever our state; nothing changes.
        if name not in self.outputs:
            self.refuse_io("no_such_output")
            log(f"SetOutput {request}: no output {name!r}")
            answer(R_NO_SUCH)
            return
        # Rule 5: refused while unbound or faulted, or while this output's previous
        # SetOutput is unanswered; the output unchanged.
        why = None
        if not self.bound:
            why = "unbound"
        elif self.status == ST_FAULT:
            why = "faulted"
        elif name in self.pending:
            why = "previous_unanswered"
        if why is not None:
            self.refuse_io(why)
            log(f"SetOutput {request} {name}={value}: refused ({why})")
            answer(R_REFUSED)
            return
        # Rule 4: takes effect when it arrives.
        old = self.outputs[name]
        self.outputs[name] = value
        self.output_set_at.setdefault((name, value), arrival)
        s["outputs_done"].append([name, value])
        log(f"SetOutput {request}: {name} {old} -> {value}")
        if name in self.actuators:
            still = self.moving_until.get(name)
            if old != value:
                self.moving_until[name] = arrival + round(self.actuators[name] * 1e6)
            elif still is None or still <= arrival:
                self.moving_until.pop(name, None)
            # The same value while it still moves toward it: answered when it has finished
            # (AMBIGUITIES.md); the same value at rest: at once.
            if name in self.moving_until:
                self.pending[name] = {
                    "request": request,
                    "value": value,
                    "arrival": arrival,
                    "entry": entry,
                }
                return
        entry["result"] = R_DONE
        answer(R_DONE)

    def answer_finished_actuators(self, now: int) -> None:
        """6.10 rule 4: an actuator's SetOutput is answered when it has finished moving,
        whatever happened meanwhile (stop, fault: the answer is still owed, rule 2)."""
        for name in [n for n, until in self.moving_until.items() if until <= now]:
            del self.moving_until[name]
            pend = self.pending.pop(name, None)
            if pend is None:
                continue
            entry = pend["entry"]
            entry["result"] = R_DONE
            entry["answer_delay_ms"] = round((now_us() - pend["arrival"]) / 1000, 3)
            self.send_io_state(pend["request"], KIND_OUTPUT, R_DONE, self.outputs[name], name,
                               pend["arrival"])
            log(f"SetOutput {pend['request']}: {name} finished moving, answered")

    def update_inputs(self, now: int) -> None:
        """The --input script: `NAME=V@S` (S s after the first accepted target) and
        `NAME=V@OUT=W+S` (S s after output OUT was first set to W)."""
        keep = []
        for item in self.input_script:
            name, value, cond = item
            at = None
            if cond[0] == "target":
                if self.first_target_us is not None:
                    at = self.first_target_us + round(cond[1] * 1e6)
            else:
                _, out, w, delay = cond
                t0 = self.output_set_at.get((out, w))
                if t0 is not None:
                    at = t0 + round(delay * 1e6)
            if at is not None and at <= now:
                if self.inputs.get(name) != value:
                    log(f"input {name} -> {value}")
                self.inputs[name] = value
                self.s["input_changes"].append([name, value])
            else:
                keep.append(item)
        self.input_script = keep

    def on_read_input(self, m: dict, arrival: int) -> None:
        """6.10 rule 3: answered at once, in every state, with the value at the answer."""
        s = self.s
        s["read_inputs_received"] += 1
        self.io_request_arrived(m)
        self.update_inputs(now_us())
        name = m["name"]
        if name in self.inputs:
            result, value = R_DONE, self.inputs[name]
        else:
            self.refuse_io("no_such_input")
            result, value = R_NO_SUCH, 0
        reads = s["inputs_read"]
        if reads and (reads[-1]["name"], reads[-1]["value"], reads[-1]["result"]) == (
            name, value, result,
        ):
            reads[-1]["count"] += 1
        else:
            reads.append({"name": name, "value": value, "result": result, "count": 1})
        self.send_io_state(m["request"], KIND_INPUT, result, value, name, arrival)

    def on_bridge_hello(self, m: dict) -> None:
        self.s["bridge_hellos"] += 1
        if m.get("_version") == 3:
            # 2.: the bridge's Hello is always version 2; 2.3 takes it with 3 (counted).
            self.s["bridge_hellos_v3"] += 1
        self.s["last_bridge_hello"] = m
        mismatch = []
        if m["names"] != [a.name for a in self.axes]:
            mismatch.append("names")
        if m["cycle_us"] != self.T:
            mismatch.append("cycle")
        if mismatch:
            log(f"bridge hello differs from this controller: {mismatch}")
        # 6.1.4: binds; resets sequence tracking; holds if moving; echo 0 (6.3).
        if self.status == ST_OK:
            self.start_hold("bridge hello")
        self.bound = True
        self.have_last = False
        self.echo = 0
        self.t_offset = None
        self.last_t = None
        self.send_hello(answer=True)

    def on_target(self, m: dict, arrival: int) -> None:
        s = self.s
        s["targets_received"] += 1
        c = self.conn
        if c is not None and not c.answer_then_feedback:
            s["targets_before_answer"] += 1
        if not self.bound:
            s["dropped_unbound"] += 1
            return
        s["targets_received_bound"] += 1
        if self.args.ignore_targets:
            s["dropped_ignored"] += 1
            return
        if self.status == ST_FAULT:
            s["dropped_faulted"] += 1
            return
        seq = m["seq"]
        if self.have_last:
            d = (seq - self.last_seq) % (1 << 32)
            if d == 0:
                s["dropped_duplicate"] += 1
                return
            if d >= 1 << 31:
                s["dropped_older"] += 1
                return
        else:
            d = 1
        pos, vel = m["pos"], m["vel"]
        refusal = self.check(pos, vel, d)
        if refusal is not None:
            code, a, b, text = refusal
            s["refused"].append({"seq": seq, "code": code, "a": a, "b": b, "text": text})
            self.latch_fault(code, a, b, text)
            return
        # Accepted.
        if not self.have_last:
            log(f"first target since the bridge Hello accepted: seq {seq}, t {m['t']}")
        if d > 1:
            s["gaps"] += 1
            s["lost_in_gaps"] += d - 1
        self.record(pos, vel, d)
        second_ok_next = d == 1
        self.ref_prev = self.ref
        self.ref = list(pos)
        self.vref = list(vel)
        self.ref_second_ok = second_ok_next
        self.have_last = True
        self.last_seq = seq
        self.echo = seq
        self.accepted_since_tick = True
        self.ever_accepted = True
        s["accepted"] += 1
        if self.first_target_us is None:
            self.first_target_us = arrival
        if s["first_accepted_seq"] is None:
            s["first_accepted_seq"] = seq
            log(f"first target accepted: seq {seq}")
        s["last_accepted_seq"] = seq
        t = m["t"]
        if self.t_offset is None:
            self.t_offset = arrival - t  # 6.2: aligned once per session
        else:
            if self.last_t is not None:
                err = abs((t - self.last_t) - d * self.T)
                if err:
                    s["t_irregular"] += 1
                    s["max_t_error_us"] = max(s["max_t_error_us"], err)
        self.last_t = t
        lateness = arrival - self.t_offset - t
        if lateness > 0:  # 6.4: arrival - offset > t
            s["late_targets"] += 1
            s["max_lateness_us"] = max(s["max_lateness_us"], lateness)
        apply_at = t + self.t_offset + self.delay_us
        if arrival > apply_at:
            s["late_past_apply_time"] += 1
        self.queue.append((apply_at, list(pos)))
        if self.status == ST_HOLDING:
            self.status = ST_OK
            self.decelerating = False
            self.wd_count = 0

    def check(self, pos: list[int], vel: list[int], d: int):
        """6.6, in the order: axis count, then per axis limits, speed and step,
        acceleration. Returns (code, a, b, text) for the first failing check."""
        if len(pos) != self.n:
            return (F_AXES, self.n, len(pos), f"{len(pos)} axes, this controller has {self.n}")
        T = self.T
        for k, a in enumerate(self.axes):
            p, v = pos[k], vel[k]
            if not a.lower <= p <= a.upper:
                return (F_LIMITS, k, 0, f"{a.name}: {p} urad outside [{a.lower}, {a.upper}]")
            if abs(v) > a.vmax:
                return (F_SPEED, k, 0, f"{a.name}: velocity {v} urad/s above {a.vmax}")
            step = abs(p - self.ref[k])
            allow = ceil_div(a.vmax * T * d, 10**6) + 1
            if step > allow:
                return (F_SPEED, k, 0, f"{a.name}: step {step} urad above {allow} (d={d})")
            dv = abs(v - self.vref[k])
            allow_v = ceil_div(a.amax * T * d, 10**6) + 1
            if dv > allow_v:
                return (F_ACCEL, k, 0, f"{a.name}: velocity change {dv} above {allow_v}")
            if d == 1 and self.ref_second_ok:
                sd = abs(p - 2 * self.ref[k] + self.ref_prev[k])
                allow_sd = ceil_div(a.amax * T * T, 10**12) + 2
                if sd > allow_sd:
                    return (F_ACCEL, k, 0, f"{a.name}: second difference {sd} above {allow_sd}")
        return None

    def record(self, pos, vel, d) -> None:
        T = self.T
        for k, a in enumerate(self.axes):
            st = self.per_axis[k]
            p, v = pos[k], vel[k]
            step = abs(p - self.ref[k])
            dv = abs(v - self.vref[k])
            if d == 1:
                st["max_step"] = max(st["max_step"], step)
                st["max_vel_change"] = max(st["max_vel_change"], dv)
            ex = step - (ceil_div(a.vmax * T * d, 10**6) + 1)
            st["max_step_excess"] = ex if st["max_step_excess"] is None else max(st["max_step_excess"], ex)
            exv = dv - (ceil_div(a.amax * T * d, 10**6) + 1)
            st["max_vel_change_excess"] = (
                exv if st["max_vel_change_excess"] is None else max(st["max_vel_change_excess"], exv)
            )
            if d == 1 and self.ref_second_ok:
                st["second_diff_checked"] += 1
                st["max_second_diff"] = max(st["max_second_diff"], abs(p - 2 * self.ref[k] + self.ref_prev[k]))
            st["max_abs_velocity"] = max(st["max_abs_velocity"], abs(v))
            st["min_position"] = p if st["min_position"] is None else min(st["min_position"], p)
            st["max_position"] = p if st["max_position"] is None else max(st["max_position"], p)

    # ---------------------------------------------------------------- the cycle

    def tick(self, now: int) -> None:
        self.s["ticks"] += 1
        self.update_inputs(now)
        self.answer_finished_actuators(now)
        c = self.conn
        # 6.5 link loss on silence: no valid frame of any kind for w cycles.
        if c is not None and not c.silence_lost and now - c.last_valid_us >= self.w * self.T:
            c.silence_lost = True
            self.link_loss("silence")
        # 6.5 target watchdog: hold in the w-th cycle in a row without a new target.
        if self.status == ST_OK:
            if self.accepted_since_tick:
                self.wd_count = 0
            else:
                self.wd_count += 1
                if self.wd_count >= self.w:
                    self.s["watchdog_holds"] += 1
                    self.start_hold("watchdog")
        self.accepted_since_tick = False
        # A local reset (6.7: unbound, holding, unprompted Hello) after N accepted targets.
        if self.args.local_reset_after and not self.local_reset_done and (
            self.s["accepted"] >= self.args.local_reset_after
        ):
            self.local_reset_done = True
            self.s["local_resets"] += 1
            self.start_hold("local reset")
            self.become_unbound()
            self.send_hello(answer=False)
        # Apply due targets (the transport delay's queue).
        new_sp = None
        while self.queue and self.queue[0][0] <= now:
            new_sp = self.queue.pop(0)[1]
        if new_sp is not None and self.status == ST_OK:
            for k in range(self.n):
                self.sp_vel[k] = new_sp[k] - self.setpoint[k]
                self.setpoint[k] = float(new_sp[k])
        elif self.decelerating:
            moving = False
            for k, a in enumerate(self.axes):
                v = self.sp_vel[k]
                dv = a.amax * self.T * self.T / 1e12
                v = v - math.copysign(min(abs(v), dv), v)
                x = self.setpoint[k] + v
                if x < a.lower or x > a.upper:
                    x = min(max(x, a.lower), a.upper)
                    v = 0.0
                self.sp_vel[k] = v
                self.setpoint[k] = x
                moving = moving or abs(v) > 1e-9
            if not moving:
                self.decelerating = False
                self.sp_vel = [0.0] * self.n
                log(f"setpoint at rest: {[round(x) for x in self.setpoint]}")
        else:
            self.sp_vel = [0.0] * self.n
        # Servo: first-order lag toward the setpoint.
        for k in range(self.n):
            self.actual[k] += self.alpha * (self.setpoint[k] - self.actual[k])
            if self.ever_accepted and self.status == ST_OK:
                err = abs(self.actual[k] - self.setpoint[k])
                st = self.per_axis[k]
                st["max_following_error"] = max(st["max_following_error"], err)
        # 6.1.3: Feedback every cycle from the first Hello on the link.
        if c is not None and c.hello_sent:
            self.send_feedback()
            if self.args.trace and self.status != ST_OK and self.s["ticks"] % 25 == 0:
                log(f"feedback status {self.status} echo {self.echo} actual {[round(x) for x in self.actual]}")

    # ---------------------------------------------------------------- I/O loop

    def accept(self, lsock: socket.socket, sel: selectors.BaseSelector) -> None:
        sock, peer = lsock.accept()
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.setblocking(False)
        if self.conn is not None:
            if self.bound and self.args.second_connection == "busy":
                # 3.5 / 8.8: a second bridge while one is bound: Fault 6, then close.
                self.s["busy_refusals"] += 1
                data = b"\x00" + frame(FAULT, bytes([F_BUSY, 0, 0, 4]) + b"busy")
                try:
                    sock.sendall(data)
                except OSError:
                    pass
                sock.close()
                log(f"refused a second bridge from {peer}: busy")
                return
            log(f"new connection replaces the current one (bound: {self.bound})")
            self.close_conn(sel, "replaced")
        self.conn = Conn(sock, peer)
        sel.register(sock, selectors.EVENT_READ, "conn")
        self.sessions_started += 1
        self.decoder.reset()
        self.become_unbound()
        self.io_next_request = 1  # 6.10 rule 1: numbered from 1 in each session
        self.send(b"\x00")  # 2.3: a sender sends one 0x00 when it opens the link
        if self.started_hello_pending:
            if self.args.unprompted_hello == "first":
                self.started_hello_pending = False
            self.send_hello(answer=False)
        log(f"session {self.sessions_started} from {peer}")

    def close_conn(self, sel: selectors.BaseSelector, why: str) -> None:
        c = self.conn
        if c is None:
            return
        try:
            sel.unregister(c.sock)
        except (KeyError, ValueError):
            pass
        try:
            c.sock.close()
        except OSError:
            pass
        self.conn = None
        self.sessions_ended += 1
        self.link_loss("transport: " + why)
        self.write_summary()

    def flush(self, sel: selectors.BaseSelector) -> None:
        c = self.conn
        if c is None or not c.out:
            return
        try:
            k = c.sock.send(c.out)
            del c.out[:k]
        except BlockingIOError:
            pass
        except OSError as e:
            self.close_conn(sel, f"send: {e}")

    def poll_conn(self, sel: selectors.BaseSelector) -> None:
        """Reads what the connection holds (until it would block), then handles it."""
        while self.conn is not None:
            try:
                data = self.conn.sock.recv(65536)
            except BlockingIOError:
                return
            except OSError as e:
                self.close_conn(sel, f"recv: {e}")
                return
            if not data:
                self.close_conn(sel, "closed by peer")
                return
            arrival = now_us()
            for mtype, m in self.decoder.push(data):
                self.on_message(mtype, m, arrival)
            self.flush(sel)

    def run(self, lsock: socket.socket) -> None:
        sel = selectors.DefaultSelector()
        lsock.setblocking(False)
        sel.register(lsock, selectors.EVENT_READ, "listen")
        next_tick = now_us() + self.T
        while not self.stop_requested:
            timeout = max(0.0, (next_tick - now_us()) / 1e6)
            events = sel.select(timeout)
            # The connection first: a close and a new connect seen in the same wake-up
            # are taken in that order, so a reconnecting bridge is not called busy.
            events.sort(key=lambda e: e[0].data == "listen")
            for key, _ in events:
                if key.data == "listen":
                    self.poll_conn(sel)
                    self.accept(lsock, sel)
                elif self.conn is not None and key.fileobj is self.conn.sock:
                    self.poll_conn(sel)
            t = now_us()
            caught_up = 0
            while t >= next_tick and caught_up < 10:
                late = t - next_tick
                if late > self.T:
                    self.s["late_ticks"] += 1
                self.s["max_tick_lateness_us"] = max(self.s["max_tick_lateness_us"], late)
                self.tick(next_tick)
                next_tick += self.T
                caught_up += 1
            if t >= next_tick:  # too far behind: resynchronise
                next_tick = t + self.T
            self.flush(sel)
            if (
                self.conn is None
                and self.args.max_sessions
                and self.sessions_ended >= self.args.max_sessions
            ):
                break
        self.write_summary()

    # ---------------------------------------------------------------- summary

    def write_summary(self) -> None:
        if not self.args.summary:
            return
        s = dict(self.s)
        s["accepted_share_of_bound"] = (
            s["accepted"] / s["targets_received_bound"] if s["targets_received_bound"] else None
        )
        s["refused_count"] = len(s["refused"])
        s["decoder"] = dict(self.decoder.c)
        s["decoder_malformed_reasons"] = dict(self.decoder.malformed_reasons)
        s["axes"] = self.per_axis
        s["controller_hello"] = {
            "names": [a.name for a in self.axes],
            "lower": [a.lower for a in self.axes],
            "upper": [a.upper for a in self.axes],
            "vmax": [a.vmax for a in self.axes],
            "amax": [a.amax for a in self.axes],
            "cycle_us": self.T,
            "watchdog": self.w,
        }
        s["outputs"] = dict(self.outputs)
        s["inputs"] = dict(self.inputs)
        s["actuators_s"] = dict(self.actuators)
        s["final_status"] = self.status
        s["final_fault"] = list(self.fault)
        s["sessions_started"] = self.sessions_started
        s["sessions_ended"] = self.sessions_ended
        tmp = self.args.summary + ".tmp"
        with open(tmp, "w") as f:
            json.dump(s, f, indent=1)
        os.replace(tmp, self.args.summary)


def parse_args(argv):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rig", default="config/irb120.toml")
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--port", type=int, default=0)
    ap.add_argument("--summary", help="JSON summary written on exit and after each session")
    ap.add_argument("--cycle-us", type=int, default=4000)
    ap.add_argument("--watchdog", type=int, default=25, help="w, in cycles")
    ap.add_argument("--delay-cycles", type=int, default=3, help="transport delay (6.2)")
    ap.add_argument("--bandwidth-hz", type=float, default=20.0, help="servo lag")
    ap.add_argument("--initial-deg", default="0,0,0,0,30,0")
    ap.add_argument("--axes", type=int)
    ap.add_argument("--limit-scale-axis", nargs=2, action="append", default=[], metavar=("AXIS", "F"))
    ap.add_argument("--lower-deg", nargs=2, action="append", default=[], metavar=("AXIS", "DEG"))
    ap.add_argument("--upper-deg", nargs=2, action="append", default=[], metavar=("AXIS", "DEG"))
    ap.add_argument("--speed-deg-s", nargs=2, action="append", default=[], metavar=("AXIS", "V"))
    ap.add_argument("--accel-deg-s2", nargs=2, action="append", default=[], metavar=("AXIS", "A"))
    ap.add_argument(
        "--set-urad", nargs=3, action="append", default=[], metavar=("FIELD", "AXIS", "V"),
        help="set a Hello wire integer directly: FIELD is lower, upper, vmax or amax",
    )
    ap.add_argument("--rename", nargs=2, action="append", default=[], metavar=("AXIS", "NAME"))
    ap.add_argument("--hold-axis-offset-deg", nargs=2, metavar=("AXIS", "DEG"))
    ap.add_argument(
        "--offset-after", type=int, default=1,
        help="with --hold-axis-offset-deg: start the offset after this many accepted targets",
    )
    ap.add_argument("--ignore-targets", action="store_true")
    ap.add_argument("--refuse-reset", action="store_true")
    ap.add_argument("--trace", action="store_true", help="log more events on stderr")
    ap.add_argument("--realtime", action="store_true", help="ask for SCHED_FIFO priority 40")
    ap.add_argument(
        "--second-connection", choices=["busy", "replace"], default="busy",
        help="a connection while one is bound: Fault 6 and close it (3.5), or drop the old one",
    )
    ap.add_argument(
        "--local-reset-after", type=int, default=0,
        help="after N accepted targets, reset locally once: hold, unbound, unprompted Hello",
    )
    ap.add_argument(
        "--unprompted-hello", choices=["first", "every", "never"], default="never",
        help="on TCP the bridge speaks first and a controller sends no unprompted Hello when a "
        "connection opens (6.1 step 2, 8.2); to test that the bridge ignores one anyway: on "
        "the first connection (the controller's start) or on every connection",
    )
    ap.add_argument("--max-sessions", type=int, default=1, help="exit after N sessions (0: never)")
    ap.add_argument(
        "--version", type=int, choices=[2, 3], default=3,
        help="the protocol version this controller speaks (6.10): 3 (Hellos with version "
        "byte 3, I/O) or 2 (a version 2 controller exactly: no I/O, version 3 frames counted "
        "as unsupported_version)",
    )
    ap.add_argument(
        "--outputs", default="gripper,lamp",
        help="the digital outputs this controller has, comma-separated (3.6 names)",
    )
    ap.add_argument(
        "--actuator", action="append", default=None, metavar="OUTPUT=SECONDS",
        help="an output that drives an actuator, answered SECONDS after its SetOutput arrived "
        "(6.10 rule 4); default gripper=0.25 (when there is a gripper output)",
    )
    ap.add_argument(
        "--inputs", default="part_held",
        help="the digital inputs this controller has, comma-separated (names given to --input "
        "are added)",
    )
    ap.add_argument(
        "--input", action="append", default=[], metavar="SCRIPT",
        help="script an input: NAME=V (its value at start), NAME=V@S (V from S seconds after "
        "the first accepted target) or NAME=V@OUTPUT=W+S (V from S seconds after the output "
        "OUTPUT was first set to W); each fires once",
    )
    a = ap.parse_args(argv)
    parse_io_args(ap, a)
    if a.hold_axis_offset_deg:
        a.hold_axis_offset_deg = (a.hold_axis_offset_deg[0], float(a.hold_axis_offset_deg[1]))
    return a


def parse_io_args(ap: argparse.ArgumentParser, a) -> None:
    def names(text: str) -> list[str]:
        out = [n for n in (x.strip() for x in text.split(",")) if n]
        for n in out:
            if not valid_io_name(n):
                ap.error(f"{n!r} is not a protocol name (3.6: 1 to 32 letters, digits, _)")
        return out

    def bit(text: str) -> int:
        if text not in ("0", "1"):
            ap.error(f"a digital value is 0 or 1, not {text!r}")
        return int(text)

    a.output_names = names(a.outputs)
    if a.actuator is None:
        a.actuator = ["gripper=0.25"] if "gripper" in a.output_names else []
    a.actuator_s = []
    for item in a.actuator:
        name, _, secs = item.partition("=")
        if name not in a.output_names:
            ap.error(f"--actuator {item}: {name!r} is not among --outputs")
        a.actuator_s.append((name, float(secs)))
    a.input_names = names(a.inputs)
    a.input_initial = []
    a.input_script = []
    for item in a.input:
        head, at, when = item.partition("@")
        name, eq, value = head.partition("=")
        if not eq or not valid_io_name(name):
            ap.error(f"--input {item}: NAME=V[@WHEN]")
        if name not in a.input_names:
            a.input_names.append(name)
        v = bit(value)
        if not at:
            a.input_initial.append((name, v))
        elif "=" in when:
            out, _, rest = when.partition("=")
            if out not in a.output_names:
                ap.error(f"--input {item}: {out!r} is not among --outputs")
            w, plus, delay = rest.partition("+")
            a.input_script.append((name, v, ("output", out, bit(w), float(delay) if plus else 0.0)))
        else:
            a.input_script.append((name, v, ("target", float(when))))


def self_test() -> int:
    """Framing against docs/protocol.md 2.2; version 1 frames (the layouts of Target,
    Feedback and Heartbeat are unchanged since) are unsupported_version; the decoder's
    counters of 2.3; then every worked example of sections 4 and 7.4 read from the doc
    itself, byte for byte, versions 2 and 3 (doc_examples_test), and 6.10's rules on a
    controller without a socket (io_rules_test)."""

    def hx(s: str) -> bytes:
        return bytes.fromhex(" ".join(s.split()))

    def body_v(version: int, mtype: int, payload: bytes) -> bytes:
        b = bytes([version, mtype]) + payload
        return b + struct.pack("<I", crc32(b))

    assert crc32(b"123456789") == 0xCBF43926
    for body, enc in [("11 22 00 33", "03 11 22 02 33"), ("00", "01 01"), ("11 00 00 00", "02 11 01 01 01")]:
        assert cobs_encode(hx(body)) == hx(enc), body
        assert cobs_decode(hx(enc)) == hx(body), enc
    for body in [bytes([7]) * 254, bytes([7]) * 254 + b"\0", bytes([7]) * 600, bytes(range(256)) * 3]:
        e = cobs_encode(body)
        assert 0 not in e and cobs_decode(e) == body
    assert cobs_encode(bytes([7]) * 254) == b"\xff" + bytes([7]) * 254
    target = struct.pack("<IQB", 42, 1500000, 6)
    target += struct.pack("<6i", 100000, -500000, 250000, 0, 1570796, -3141593)
    target += struct.pack("<6i", 10000, -20000, 0, 500000, 0, -1000000)
    target_frame = hx(
        """04 01 02 2a 01 01 04 60 e3 16 01 01 01 01 05 06
        a0 86 01 08 e0 5e f8 ff 90 d0 03 01 01 01 01 04
        ec f7 17 07 27 10 d0 ff 10 27 01 05 e0 b1 ff ff
        01 01 01 04 20 a1 07 01 01 01 01 09 c0 bd f0 ff
        c0 30 2d f0 00"""
    )
    assert cobs_encode(body_v(1, TARGET, target)) + b"\0" == target_frame
    feedback = struct.pack("<IBBBBB", 42, 0, 0, 0, 0, 6)
    feedback += struct.pack("<6i", 99512, -499007, 249875, 0, 1570013, -3140911)
    feedback_frame = hx(
        """04 01 06 2a 01 01 01 01 01 01 05 06 b8 84 01 08
        c1 62 f8 ff 13 d0 03 01 01 01 01 04 dd f4 17 09
        d1 12 d0 ff 07 0e 1a 1c 00"""
    )
    assert cobs_encode(body_v(1, FEEDBACK, feedback)) + b"\0" == feedback_frame
    assert cobs_encode(body_v(1, HEARTBEAT, b"")) + b"\0" == hx("07 01 05 31 d7 a8 28 00")
    assert [deg_to_urad(x) for x in (-165, 70, 250, 320, 420)] == [
        -2879793, 1221730, 4363323, 5585054, 7330383
    ]
    # 2.3: a v1 frame is unsupported_version; a v2 one decodes; counters.
    d = Decoder()
    assert d.push(target_frame) == [] and d.c["unsupported_version"] == 1
    good = cobs_encode(body_v(2, TARGET, target)) + b"\0"
    msgs = d.push(b"\0\0" + good)
    assert len(msgs) == 1 and msgs[0][1]["seq"] == 42 and d.c["frames"] == 1
    bad_crc = bytearray(body_v(2, TARGET, target))
    bad_crc[10] ^= 1
    d.push(cobs_encode(bytes(bad_crc)) + b"\0")
    assert d.c["crc_errors"] == 1
    d.push(cobs_encode(body_v(2, TARGET, target + b"\1")) + b"\0")  # a byte too many
    d.push(cobs_encode(body_v(2, 0x09, b"")) + b"\0")  # reserved type
    d.push(cobs_encode(body_v(2, STOP, b"\0")) + b"\0")  # payload on Stop
    d.push(cobs_encode(body_v(2, HELLO, b"\0" + struct.pack("<IIB", 4000, 25, 2))) + b"\0")
    d.push(b"\x05\x01\0")  # COBS running past the end
    assert d.c["malformed"] == 5, d.c
    d.push(cobs_encode(b"\2\5\0") + b"\0")  # too short
    d.push(bytes([1]) * 2000 + b"\0")  # too long: dropped at 1608 bytes
    assert d.c["oversized"] == 2, d.c
    assert d.push(good) and d.c["frames"] == 2
    assert d.c["overruns"] == 0
    n_examples = doc_examples_test()
    io_rules_test()
    print(f"self-test ok ({n_examples} worked examples of docs/protocol.md matched byte for byte)")
    return 0


DOC = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "docs", "protocol.md")


def doc_examples() -> dict[str, list[str]]:
    """Section 4 and 7.4/7.5 of docs/protocol.md: every `<!-- example: NAME -->` block, as
    its lines with the comments (after `#`, not in CAN lines) removed."""
    import re

    with open(DOC, encoding="utf-8") as f:
        text = f.read()
    out = {}
    for m in re.finditer(r"<!-- example: ([\w-]+) -->\s*```text\n(.*?)```", text, re.S):
        out[m.group(1)] = [ln for ln in m.group(2).splitlines() if ln.strip()]
    return out


def example_bytes(lines: list[str]) -> bytes:
    return bytes.fromhex(" ".join(ln.split("#", 1)[0] for ln in lines))


def doc_examples_test() -> int:
    """Encodes the values the doc states for each worked example and compares with the doc's
    bytes; decodes the doc's bytes back to those values (a version 3 receiver; a version 2
    receiver for the version 2 layouts). Returns the number of examples checked."""
    ex = doc_examples()
    checked = 0

    def same(name: str, got: bytes) -> None:
        nonlocal checked
        want = example_bytes(ex[name])
        assert got == want, f"{name}:\n got  {got.hex(' ')}\n want {want.hex(' ')}"
        checked += 1

    def decode_one(frame_bytes: bytes, version: int = 3) -> tuple[int, dict]:
        d = Decoder(version)
        msgs = d.push(b"\0" + frame_bytes)
        assert len(msgs) == 1, (frame_bytes.hex(" "), d.c, d.malformed_reasons)
        return msgs[0]

    def body_and_frame(name: str, mtype: int, payload: bytes, version: int | None = None) -> bytes:
        body = body_of(mtype, payload, version)
        same(f"{name}-body", body)
        fr = cobs_encode(body) + b"\0"
        if f"{name}-frame" in ex:
            same(f"{name}-frame", fr)
        return fr

    # Version 2 layouts (section 4).
    target = struct.pack("<IQB", 42, 1500000, 6)
    target += struct.pack("<6i", 100000, -500000, 250000, 0, 1570796, -3141593)
    target += struct.pack("<6i", 10000, -20000, 0, 500000, 0, -1000000)
    fr = body_and_frame("target-6", TARGET, target)
    for v in (2, 3):
        mt, m = decode_one(fr, v)
        assert mt == TARGET and m["seq"] == 42 and m["t"] == 1500000 and m["vel"][5] == -1000000
    feedback = struct.pack("<IBBBBB", 42, 0, 0, 0, 0, 6)
    feedback += struct.pack("<6i", 99512, -499007, 249875, 0, 1570013, -3140911)
    fr = body_and_frame("feedback-6", FEEDBACK, feedback)
    assert decode_one(fr)[1]["seq"] == 42
    fr = body_and_frame("heartbeat", HEARTBEAT, b"")
    assert decode_one(fr) == (HEARTBEAT, {"_version": 2})
    lims = [
        (-2879793, 2879793, 4363323, 17453293),
        (-1919862, 1919862, 4363323, 17453293),
        (-1919862, 1221730, 4363323, 17453293),
        (-2792527, 2792527, 5585054, 22340214),
        (-2094395, 2094395, 5585054, 22340214),
        (-6981317, 6981317, 7330383, 29321531),
    ]
    hello = bytearray([6])
    for k in range(6):
        hello += bytes([7]) + f"joint_{k + 1}".encode()
    for row in lims:
        hello += struct.pack("<iiii", *row)
    hello += struct.pack("<IIB", 4000, 25, 1)
    fr = body_and_frame("hello-6", HELLO, bytes(hello))
    mt, m = decode_one(fr)
    assert mt == HELLO and m["answer"] and m["_version"] == 2 and m["amax"][5] == 29321531
    fault = bytes([2, 2, 0, 11]) + b"axis 3 step"
    body_and_frame("fault", FAULT, fault)
    # The degrees of config/irb120.toml on the wire (the Hello's values).
    assert [deg_to_urad(x) for x in (-165, 70, 250, 320, 420)] == [
        -2879793, 1221730, 4363323, 5585054, 7330383
    ]

    # Version 3 (section 4, "I/O (version 3)").
    fr = body_and_frame("set-output", SET_OUTPUT, set_output_payload(7, 1, "gripper"))
    mt, m = decode_one(fr)
    assert (mt, m) == (SET_OUTPUT, {"request": 7, "name": "gripper", "value": 1, "_version": 3})
    d2 = Decoder(2)
    assert d2.push(fr) == [] and d2.c["unsupported_version"] == 1  # 2.3 check 3
    out_state = io_state_payload(7, KIND_OUTPUT, R_DONE, 1, "gripper")
    fr = body_and_frame("io-state-output", IO_STATE, out_state)
    assert decode_one(fr)[1] == {
        "request": 7, "name": "gripper", "kind": 0, "result": 0, "value": 1, "_version": 3
    }
    fr = body_and_frame("read-input", READ_INPUT, read_input_payload(8, "part_held"))
    assert decode_one(fr) == (READ_INPUT, {"request": 8, "name": "part_held", "_version": 3})
    in_state = io_state_payload(8, KIND_INPUT, R_DONE, 1, "part_held")
    fr = body_and_frame("io-state-input", IO_STATE, in_state)
    assert decode_one(fr)[1]["kind"] == 1
    # "A version 3 controller's Hello is the Hello above with its first byte 03 instead of
    # 02 (and so another CRC); nothing else in it changes."
    v2_body = example_bytes(ex["hello-6-body"])
    v3_body = body_of(HELLO, bytes(hello), version=3)
    assert v3_body[0] == 3 and v3_body[1:-4] == v2_body[1:-4]
    assert v3_body[-4:] == struct.pack("<I", crc32(b"\x03" + v2_body[1:-4]))
    mt, m = decode_one(cobs_encode(v3_body) + b"\0")
    assert mt == HELLO and m["_version"] == 3
    d2 = Decoder(2)
    assert d2.push(cobs_encode(v3_body) + b"\0") == [] and d2.c["unsupported_version"] == 1
    # 7.4: the SetOutput in classic CAN segments on offset 0x28, base 0x100.
    segs = can_segments(0x100, 0x28, body_of(SET_OUTPUT, set_output_payload(7, 1, "gripper")))
    want = []
    for ln in ex["set-output-can"]:
        cid, data = ln.strip().split("#")
        want.append((int(cid, 16), bytes.fromhex(data)))
    assert segs == want, (segs, want)
    checked += 1
    missing = {
        "set-output-body", "set-output-frame", "io-state-output-body", "read-input-body",
        "io-state-input-body", "io-state-input-frame", "set-output-can",
    } - set(ex)
    assert not missing, f"docs/protocol.md lost examples {missing}"

    # 2.3 / 3.6: what a version 3 receiver takes and drops.
    def counts(body: bytes, version: int = 3) -> dict:
        d = Decoder(version)
        msgs = d.push(cobs_encode(body) + b"\0")
        return {"ok": len(msgs), **{k: v for k, v in d.c.items() if v and k not in ("frames", "bytes_discarded")}}

    def raw_body(version: int, mtype: int, payload: bytes) -> bytes:
        b = bytes([version, mtype]) + payload
        return b + struct.pack("<I", crc32(b))

    ok = {"ok": 1}
    bad = {"ok": 0, "malformed": 1}
    assert counts(raw_body(3, TARGET, target)) == ok  # 0x01-0x08 with version byte 3
    assert counts(raw_body(3, HEARTBEAT, b"")) == ok
    assert counts(raw_body(2, SET_OUTPUT, set_output_payload(7, 1, "gripper"))) == bad
    assert counts(raw_body(2, READ_INPUT, read_input_payload(8, "x")), version=2) == bad
    assert counts(raw_body(4, HEARTBEAT, b"")) == {"ok": 0, "unsupported_version": 1}
    assert counts(raw_body(3, HEARTBEAT, b""), version=2) == {"ok": 0, "unsupported_version": 1}
    assert counts(raw_body(3, 0x0C, b"")) == bad  # reserved
    for payload in [
        struct.pack("<IB", 7, 1) + b"\x00",  # name length 0
        struct.pack("<IB", 7, 1) + b"\x21" + b"a" * 33,  # over 32
        struct.pack("<IB", 7, 1) + b"\x04grip-",  # `-`, and one byte too many
        struct.pack("<IB", 7, 1) + b"\x04gr p",  # a space
        struct.pack("<IB", 7, 1) + b"\x04gr\xc3\xa9",  # not ASCII
        struct.pack("<IB", 7, 2) + b"\x04grip",  # value 2
        struct.pack("<IB", 0, 1) + b"\x04grip",  # request 0
        struct.pack("<IB", 7, 1) + b"\x05grip",  # a byte too few
        struct.pack("<I", 7),  # no name
    ]:
        assert counts(raw_body(3, SET_OUTPUT, payload)) == bad, payload
    assert counts(raw_body(3, SET_OUTPUT, set_output_payload(7, 0, "A_b9" * 8))) == ok  # 32
    assert counts(raw_body(3, READ_INPUT, read_input_payload(0, "x"))) == bad
    assert counts(raw_body(3, READ_INPUT, read_input_payload(1, "x") + b"\0")) == bad
    for kind, result, value in [(2, 0, 0), (0, 3, 0), (0, 0, 2)]:
        p = struct.pack("<IBBB", 5, kind, result, value) + b"\x01x"
        assert counts(raw_body(3, IO_STATE, p)) == bad, (kind, result, value)
    assert counts(raw_body(3, IO_STATE, io_state_payload(5, 1, 2, 0, "x"))) == ok
    return checked


class _Probe:
    """A controller without a socket, for io_rules_test: what it sends is decoded back."""

    def __init__(self, extra: list[str]) -> None:
        rig = os.path.join(os.path.dirname(DOC), "..", "config", "irb120.toml")
        args = parse_args(["--rig", rig, *extra])
        self.ctl = Controller(args, load_axes(args))
        self.ctl.conn = Conn(None, "probe")
        self.ctl.sessions_started = 1
        self.rx = Decoder(3)
        self.t = now_us()

    def send(self, mtype: int, payload: bytes, version: int | None = None) -> list:
        for mt, m in Decoder(3).push(frame(mtype, payload, version)):
            self.ctl.on_message(mt, m, now_us())
        return self.take()

    def take(self) -> list:
        out = [x for x in self.rx.push(bytes(self.ctl.conn.out)) if x[0] != FEEDBACK]
        self.ctl.conn.out.clear()
        return out

    def tick(self, seconds: float) -> list:
        end = now_us() + round(seconds * 1e6)
        while True:
            self.ctl.conn.last_valid_us = now_us()  # as if the bridge's Heartbeats came
            self.ctl.tick(now_us())
            if now_us() >= end:
                return self.take()
            time.sleep(self.ctl.T / 1e6)


def io_rules_test() -> None:
    """6.10's rules on a socketless controller (version 3), and version 2's refusal of I/O."""

    def st(request, kind, result, value, name):
        return (IO_STATE, {"request": request, "kind": kind, "result": result, "value": value,
                           "name": name, "_version": 3})

    p = _Probe(["--actuator", "gripper=0.05", "--input", "part_held=1@gripper=1+0.02"])
    c = p.ctl
    hello = p.send(HELLO, c.hello_payload(False))  # the rig's own Hello, as the bridge's
    assert [m[0] for m in hello] == [HELLO]
    c.bound = False  # rule 5: unbound
    assert p.send(SET_OUTPUT, set_output_payload(1, 1, "lamp")) == [st(1, 0, 2, 0, "lamp")]
    assert c.outputs["lamp"] == 0
    # Rule 3: reads in every state; rule 6: unknown names, whatever the state.
    assert p.send(READ_INPUT, read_input_payload(2, "part_held")) == [st(2, 1, 0, 0, "part_held")]
    assert p.send(READ_INPUT, read_input_payload(3, "lamp")) == [st(3, 1, 1, 0, "lamp")]
    assert p.send(SET_OUTPUT, set_output_payload(4, 1, "part_held")) == [st(4, 0, 1, 0, "part_held")]
    c.bound = True
    # Rule 4: a plain output at once; an actuator when it has finished.
    assert p.send(SET_OUTPUT, set_output_payload(5, 1, "lamp")) == [st(5, 0, 0, 1, "lamp")]
    assert p.send(SET_OUTPUT, set_output_payload(6, 1, "gripper")) == []
    assert c.outputs["gripper"] == 1  # takes effect when it arrives
    # Rule 5: the same output's previous SetOutput unanswered: refused, unchanged.
    assert p.send(SET_OUTPUT, set_output_payload(7, 0, "gripper")) == [st(7, 0, 2, 0, "gripper")]
    assert c.outputs["gripper"] == 1
    # Rule 7: outputs kept through EStop; the owed answer still comes (rule 2).
    assert [m[0] for m in p.send(ESTOP, b"")] == [FAULT]
    assert p.send(SET_OUTPUT, set_output_payload(8, 0, "lamp")) == [st(8, 0, 2, 0, "lamp")]
    assert p.tick(0.1) == [st(6, 0, 0, 1, "gripper")]
    assert c.outputs == {"gripper": 1, "lamp": 1}
    # The scripted input: part_held 1 from 0.02 s after gripper was set to 1.
    assert p.send(READ_INPUT, read_input_payload(9, "part_held")) == [st(9, 1, 0, 1, "part_held")]
    # Reset: unbound, unprompted Hello with version byte 3 (6.10), outputs kept.
    out = p.send(RESET, b"")
    assert [(m[0], m[1]["_version"], m[1]["answer"]) for m in out] == [(HELLO, 3, False)]
    assert p.send(SET_OUTPUT, set_output_payload(10, 0, "gripper")) == [st(10, 0, 2, 0, "gripper")]
    assert [m[0] for m in p.send(HELLO, c.hello_payload(False))] == [HELLO]
    # The same value at rest: at once; link loss keeps outputs and drops owed answers.
    assert p.send(SET_OUTPUT, set_output_payload(11, 1, "gripper")) == [st(11, 0, 0, 1, "gripper")]
    assert p.send(SET_OUTPUT, set_output_payload(12, 0, "gripper")) == []
    c.link_loss("probe")
    assert p.tick(0.1) == [] and c.outputs["gripper"] == 0
    assert c.s["io_answers_dropped_link_loss"] == 1
    assert c.s["outputs_done"] == [["lamp", 1], ["gripper", 1], ["gripper", 1], ["gripper", 0]]
    assert [e["result"] for e in c.s["outputs_set"]] == [
        2, 1, 0, 0, 2, 2, 2, 0, "dropped_link_loss"
    ]
    # Rule 8: I/O does not feed the target watchdog (nothing here resets wd_count).
    # Version 2: the Hello carries version byte 2 and I/O frames are not for it.
    p2 = _Probe(["--version", "2"])
    out = p2.send(HELLO, p2.ctl.hello_payload(False))
    assert [(m[0], m[1]["_version"]) for m in out] == [(HELLO, 2)]
    p2.ctl.decoder.push(frame(SET_OUTPUT, set_output_payload(1, 1, "gripper")))
    assert p2.ctl.decoder.c["unsupported_version"] == 1


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv == ["--self-test"]:
        return self_test()
    args = parse_args(argv)
    axes = load_axes(args)
    ctl = Controller(args, axes)

    def on_term(signum, frame_):
        ctl.stop_requested = True

    if args.realtime:
        # Best effort: a 4 ms cycle on a busy machine (the bridge's cycle does the same).
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(40))
        except (AttributeError, PermissionError, OSError) as e:
            log(f"no SCHED_FIFO ({e}); running at normal priority")
    signal.signal(signal.SIGTERM, on_term)
    signal.signal(signal.SIGINT, on_term)
    lsock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    lsock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    lsock.bind((args.host, args.port))
    lsock.listen(4)
    print(lsock.getsockname()[1], flush=True)
    log(
        f"listening on {args.host}:{lsock.getsockname()[1]}, {len(axes)} axes, "
        f"cycle {args.cycle_us} us, watchdog {args.watchdog}"
    )
    ctl.run(lsock)
    lsock.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
