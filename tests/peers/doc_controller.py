#!/usr/bin/env python3
"""A strict robot controller for the rigbridge wire protocol, version 2.

Written from docs/protocol.md alone (no look at the bridge's code), as an independent
vendor would: a TCP server that speaks COBS/CRC-32 framing, answers the bridge's Hello,
checks every Target on the wire integers (6.6), latches faults, runs a watchdog and a
simple servo model on its own 4 ms clock, and writes a JSON summary when the bridge
disconnects or on SIGTERM.

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

VERSION = 2
MAX_AXES = 32
MAX_BODY_LEN = 1600
MAX_COBS_LEN = 1607  # MAX_FRAME_LEN less the delimiter (2.3)
T_LIMIT = 1 << 48

HELLO, TARGET, STOP, ESTOP, HEARTBEAT, FEEDBACK, FAULT, RESET = range(1, 9)
TYPE_NAMES = {
    HELLO: "hello",
    TARGET: "target",
    STOP: "stop",
    ESTOP: "estop",
    HEARTBEAT: "heartbeat",
    FEEDBACK: "feedback",
    FAULT: "fault",
    RESET: "reset",
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


def frame(msg_type: int, payload: bytes) -> bytes:
    body = bytes([VERSION, msg_type]) + payload
    body += struct.pack("<I", crc32(body))
    return cobs_encode(body) + b"\x00"


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
    raise Malformed(f"reserved type 0x{msg_type:02x}")


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
    """2.3 Receiving, with the bridge's counters."""

    def __init__(self) -> None:
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
        if body[0] != VERSION:
            self._bad("unsupported_version", raw)
            return None
        try:
            fields = decode_payload(body[1], body[2:-4])
        except Malformed as e:
            self._bad("malformed", raw, str(e))
            return None
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
        self.decoder = Decoder()
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
        self.send(frame(HELLO, self.hello_payload(answer)))
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
        else:
            # Feedback or Fault from the bridge: wrong side, ignored (3.).
            self.s["wrong_side_messages"] += 1

    def on_bridge_hello(self, m: dict) -> None:
        self.s["bridge_hellos"] += 1
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
    a = ap.parse_args(argv)
    if a.hold_axis_offset_deg:
        a.hold_axis_offset_deg = (a.hold_axis_offset_deg[0], float(a.hold_axis_offset_deg[1]))
    return a


def self_test() -> int:
    """Framing against docs/protocol.md 2.2 and section 4 (whose examples carry version
    byte 1: the layouts of Target, Feedback and Heartbeat are unchanged in v2), and the
    decoder's counters of 2.3."""

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
    print("self-test ok")
    return 0


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
