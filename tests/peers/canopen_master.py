"""A CANopen master written with python canopen (PyPI `canopen`, RemoteNode, on `python-can`
socketcan) against rigbridge's twin drives (`rigbridge twin --canopen`), for
tests/canopen.rs.

It does what a CSP master does, all through the library: NMT reset communication and the
boot-ups, SDO reads (device type, statusword, position), SDO writes (mode 8, the
interpolation period, the heartbeat), the PDO remapping of RPDO1 and TPDO1 with the
library's own `PdoMap.save()`, NMT start, the power steps 0x06, 0x07, 0x0F with the
statusword read after each, then a smooth move of every axis with RPDO1 + SYNC each period,
TPDO1 read back after each SYNC. It also tries what a strict drive must refuse (a mode that
is not CSP, a mapping written while its PDO is valid) and expects SDO aborts. Prints one JSON
object: what it saw, and `errors` (empty when every step went as CiA 301/402 say).

usage: canopen_master.py --channel vcan0 --eds FILE --nodes 1,2,3 --period-ms 10
                         --move-counts N --seconds S
"""

import argparse
import json
import math
import sys
import time

import canopen
from canopen.sdo.exceptions import SdoAbortedError

ENABLED_MASK, ENABLED = 0x6F, 0x27
SDO_TIMEOUT_S = 3.0


def state_of(word):
    if word & 0x4F == 0x40:
        return "switch on disabled"
    if word & 0x4F == 0x08:
        return "fault"
    return {0x21: "ready to switch on", 0x23: "switched on", 0x27: "operation enabled"}.get(
        word & 0x6F, hex(word)
    )


def set_up(node, period_ms, errors):
    if node.sdo[0x1000].raw & 0xFFFF != 402:
        errors.append(f"node {node.id}: device type {node.sdo[0x1000].raw:#x}")
    node.sdo[0x6060].raw = 8
    node.sdo[0x60C2][1].raw = period_ms
    node.sdo[0x60C2][2].raw = -3
    if node.sdo[0x6061].raw != 8:
        errors.append(f"node {node.id}: mode display {node.sdo[0x6061].raw}")
    for refused, what in (
        (lambda: setattr(node.sdo[0x6060], "raw", 1), "mode 1 (not CSP)"),
        (lambda: setattr(node.sdo[0x1600][1], "raw", 0x60400010), "a mapping of a valid PDO"),
    ):
        try:
            refused()
            errors.append(f"node {node.id}: {what} was accepted")
        except SdoAbortedError:
            pass
    node.rpdo.read()
    node.tpdo.read()
    rpdo, tpdo = node.rpdo[1], node.tpdo[1]
    rpdo.clear()
    rpdo.add_variable(0x6040)
    rpdo.add_variable(0x607A)
    rpdo.trans_type = 1
    rpdo.enabled = True
    tpdo.clear()
    tpdo.add_variable(0x6041)
    tpdo.add_variable(0x6064)
    tpdo.trans_type = 1
    tpdo.enabled = True
    node.rpdo.save()
    node.tpdo.save()
    node.sdo[0x1017].raw = 100


def power_up(node, errors):
    node.sdo[0x607A].raw = node.sdo[0x6064].raw
    for command, expected in ((0x06, "ready to switch on"), (0x07, "switched on"), (0x0F, "operation enabled")):
        node.sdo[0x6040].raw = command
        got = state_of(node.sdo[0x6041].raw)
        if got != expected:
            errors.append(f"node {node.id}: controlword {command:#04x} left it {got}")


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--channel", default="vcan0")
    parser.add_argument("--eds", required=True)
    parser.add_argument("--nodes", required=True)
    parser.add_argument("--period-ms", type=int, default=10)
    parser.add_argument("--move-counts", type=int, default=20000)
    parser.add_argument("--seconds", type=float, default=2.0)
    args = parser.parse_args()
    errors = []
    network = canopen.Network()
    network.connect(interface="socketcan", channel=args.channel)
    nodes = []
    for node_id in (int(n) for n in args.nodes.split(",")):
        node = canopen.RemoteNode(node_id, args.eds)
        # The library's 0.3 s is short for an interpreter under the VM's emulation, with a
        # backlog of TPDOs in front of the answer.
        node.sdo.RESPONSE_TIMEOUT = SDO_TIMEOUT_S
        network.add_node(node)
        nodes.append(node)
    for node in nodes:
        node.nmt.send_command(0x82)
    # The boot-up may come before a wait for it starts: read each node until it answers.
    for node in nodes:
        deadline = time.time() + 5
        while True:
            try:
                node.sdo[0x1000].raw
                break
            except Exception:
                if time.time() > deadline:
                    raise
    for node in nodes:
        set_up(node, args.period_ms, errors)
    for node in nodes:
        node.nmt.state = "OPERATIONAL"
    starts = [node.sdo[0x6064].raw for node in nodes]
    for node in nodes:
        power_up(node, errors)
    heartbeats = []
    for node in nodes:
        node.nmt.wait_for_heartbeat(2)
        heartbeats.append(node.nmt.state)
    # A smooth move: a cosine ramp of move_counts over `seconds`, one point a period.
    period = args.period_ms / 1000.0
    steps = int(args.seconds / period)
    feedback = 0
    last_positions = list(starts)
    for k in range(1, steps + 1):
        share = 0.5 - 0.5 * math.cos(math.pi * k / steps)
        for node, start in zip(nodes, starts):
            node.rpdo[1]["Controlword"].raw = 0x0F
            node.rpdo[1]["Target position"].raw = start + int(round(share * args.move_counts))
            node.rpdo[1].transmit()
        for node in nodes:
            node.tpdo[1].is_received = False
        sent = time.time()
        network.sync.transmit()
        # Each drive's TPDO1 answers the SYNC (transmission type 1).
        while time.time() < sent + 0.5 and not all(n.tpdo[1].is_received for n in nodes):
            time.sleep(0.0005)
        for i, node in enumerate(nodes):
            if not node.tpdo[1].is_received:
                errors.append(f"node {node.id}: no TPDO1 after SYNC {k}")
                continue
            feedback += 1
            last_positions[i] = node.tpdo[1]["Position actual value"].raw
            word = node.tpdo[1]["Statusword"].raw
            if word & 0x08:
                errors.append(f"node {node.id}: fault at point {k} ({word:#06x})")
        rest = period - (time.time() - sent)
        if rest > 0:
            time.sleep(rest)
    # Settle: SYNCs without new targets until the drives are within 2 counts of the end.
    for _ in range(100):
        network.sync.transmit()
        time.sleep(period)
    time.sleep(0.5)
    final = [node.sdo[0x6064].raw for node in nodes]
    words = [node.sdo[0x6041].raw for node in nodes]
    for node, start, end, word in zip(nodes, starts, final, words):
        if abs(end - (start + args.move_counts)) > 2:
            errors.append(f"node {node.id}: ended at {end}, not {start + args.move_counts}")
        if word & ENABLED_MASK != ENABLED:
            errors.append(f"node {node.id}: ended {state_of(word)}")
    network.disconnect()
    print(json.dumps({
        "nodes": [n.id for n in nodes],
        "starts": starts,
        "final": final,
        "statuswords": words,
        "heartbeat_states": heartbeats,
        "points": steps,
        "tpdos": feedback,
        "errors": errors,
    }), flush=True)
    return 0 if not errors else 1


if __name__ == "__main__":
    sys.exit(main())
