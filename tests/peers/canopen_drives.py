"""CiA 402 drives simulated with python canopen's LocalNode (PyPI `canopen`, on `python-can`
socketcan), for tests/canopen.rs: rigbridge's CANopen link is the master.

The library does the CANopen: the object dictionary (tests/peers/cia402_csp.eds), the SDO
server, the NMT slave and heartbeat producer, the PDO maps as the master configures them
through SDO (read back with RemoteNode-style `pdo.read()` at NMT start). This script adds
only what a drive's firmware would: boot-up and pre-operational after an NMT reset, the
CiA 402 power state machine on the controlword, and cyclic synchronous position: at each
SYNC the position is measured and the TPDO goes out, then the last RPDO's target is taken.
With `--lag-ms 0` the drive is at the target it took by the next SYNC; with `--lag-ms T` it
follows as a servo does, a first-order lag of time constant T over each interpolation
period (0x60C2), so the position measured at a SYNC lags the target taken at the one before.

It records what the master did and prints one JSON object when it ends (SIGTERM or
--seconds): the order of the SDO writes (checked against the CiA 301 PDO remapping
procedure), the mode and period written, the controlwords, the largest step and second
difference of the targets per axis (counts per SYNC), the lowest and highest target, the
largest |position measured - target held when measured| (counts), SYNC intervals, and errors.

usage: canopen_drives.py --channel vcan0 --eds FILE --nodes 1,2,3 --start C1,C2,C3
                         [--lag-ms T] [--seconds S] [--fault-after-syncs N --fault-axis A]
"""

import argparse
import json
import math
import signal
import struct
import sys
import threading
import time

import canopen

# CiA 402-2 statusword patterns (table 8), with bit 9 (remote).
SWITCH_ON_DISABLED = 0x0250
READY = 0x0231
SWITCHED_ON = 0x0233
ENABLED = 0x0237
QUICK_STOP = 0x0217
FAULT = 0x0218


class Drive:
    def __init__(self, network, node_id, eds, start, lag_s):
        self.node = canopen.LocalNode(node_id, eds)
        network.add_node(self.node)
        self.network = network
        self.id = node_id
        self.status = SWITCH_ON_DISABLED
        self.controlword = 0
        self.actual = start
        # Where the position is, unrounded: the servo's own state.
        self.position = float(start)
        self.lag_s = lag_s
        # 0x60C2 sub 1 and 2, the EDS's defaults until written: 1 ms.
        self.interpolation = [1, -3]
        self.target = None
        self.lowest = None
        self.highest = None
        self.max_following = 0
        self.history = [start, start]
        self.max_step = 0
        self.max_second = 0
        self.targets = 0
        self.writes = []
        self.controlwords = []
        self.errors = []
        self.rpdo = None
        self.tpdo = None
        self.operational = False
        self.node.add_write_callback(self.on_write)
        self.store()

    def store(self):
        self.node.set_data(0x6041, 0, struct.pack("<H", self.status))
        self.node.set_data(0x6064, 0, struct.pack("<i", int(self.actual)))

    def on_write(self, index, subindex, od, data, **kwargs):
        if index in (0x6041, 0x6064, 0x6061):
            return
        signed = index in (0x6060, 0x607A) or (index, subindex) == (0x60C2, 2)
        value = int.from_bytes(data, "little", signed=signed)
        self.writes.append([index, subindex, value])
        if index == 0x6060:
            self.node.set_data(0x6061, 0, data)
        if index == 0x60C2:
            self.interpolation[subindex - 1] = value
        if index == 0x6040:
            self.on_controlword(value, "sdo")

    def on_controlword(self, word, via):
        rising_reset = word & 0x80 and not self.controlword & 0x80
        self.controlword = word
        if via == "sdo":
            self.controlwords.append(word)
        s = self.status
        if s == FAULT:
            nxt = SWITCH_ON_DISABLED if rising_reset else FAULT
        elif word & 0x82 == 0x00:
            nxt = SWITCH_ON_DISABLED
        elif word & 0x86 == 0x02:
            nxt = QUICK_STOP if s == ENABLED else SWITCH_ON_DISABLED
        elif word & 0x87 == 0x06:
            nxt = READY if s in (SWITCH_ON_DISABLED, SWITCHED_ON, ENABLED) else s
        elif word & 0x8F == 0x07:
            nxt = SWITCHED_ON if s in (READY, ENABLED) else s
        elif word & 0x8F == 0x0F:
            nxt = {READY: SWITCHED_ON, SWITCHED_ON: ENABLED}.get(s, s)
        else:
            nxt = s
        if nxt == ENABLED and s != ENABLED:
            self.history = [self.actual, self.actual]
            self.target = None
        self.status = nxt
        self.store()

    def on_nmt(self, command):
        if command in (0x81, 0x82):
            self.operational = False
            self.network.send_message(0x700 + self.id, bytes([0]))
            self.node.nmt.state = "PRE-OPERATIONAL"
        elif command == 0x01:
            # The maps as the master wrote them through SDO.
            self.node.rpdo.read()
            self.node.tpdo.read()
            self.rpdo = self.node.rpdo[1]
            self.tpdo = self.node.tpdo[1]
            self.operational = True
        elif command in (0x02, 0x80):
            self.operational = False

    def period_s(self):
        """The interpolation period 0x60C2 as the master wrote it (s)."""
        return self.interpolation[0] * 10.0 ** self.interpolation[1]

    def servo(self):
        """One interpolation period of following the target taken at the last SYNC."""
        if self.target is None or self.status != ENABLED:
            return
        if self.lag_s > 0:
            self.position += (self.target - self.position) * (1 - math.exp(-self.period_s() / self.lag_s))
        else:
            self.position = float(self.target)
        self.actual = int(round(self.position))
        self.max_following = max(self.max_following, abs(self.actual - self.target))
        self.store()

    def on_sync(self):
        if not self.operational:
            return
        self.servo()
        if self.tpdo is not None and self.tpdo.enabled and 1 <= self.tpdo.trans_type <= 240:
            self.tpdo["Statusword"].raw = self.status
            self.tpdo["Position actual value"].raw = int(self.actual)
            self.tpdo.transmit()
        rpdo = self.rpdo
        if rpdo is not None and rpdo.is_received:
            rpdo.is_received = False
            self.on_controlword(rpdo["Controlword"].raw, "rpdo")
            if self.status == ENABLED:
                self.take(rpdo["Target position"].raw)

    def take(self, target):
        before, last = self.history
        self.max_step = max(self.max_step, abs(target - last))
        self.max_second = max(self.max_second, abs(target - 2 * last + before))
        self.history = [last, target]
        self.targets += 1
        self.target = target
        self.lowest = target if self.lowest is None else min(self.lowest, target)
        self.highest = target if self.highest is None else max(self.highest, target)

    def fault(self):
        self.status = FAULT
        self.node.set_data(0x1001, 0, bytes([1]))
        self.store()
        self.node.emcy.send(0x5000, 1)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--channel", default="vcan0")
    parser.add_argument("--eds", required=True)
    parser.add_argument("--nodes", required=True)
    parser.add_argument("--start", required=True)
    parser.add_argument("--lag-ms", type=float, default=0.0)
    parser.add_argument("--seconds", type=float, default=120.0)
    parser.add_argument("--fault-after-syncs", type=int, default=0)
    parser.add_argument("--fault-axis", type=int, default=1)
    args = parser.parse_args()
    nodes = [int(n) for n in args.nodes.split(",")]
    starts = [int(c) for c in args.start.split(",")]
    network = canopen.Network()
    network.connect(interface="socketcan", channel=args.channel)
    drives = [Drive(network, n, args.eds, s, args.lag_ms / 1e3) for n, s in zip(nodes, starts)]
    syncs = []
    streamed = [0]
    faulted_at = [None]
    lock = threading.Lock()

    def on_nmt(can_id, data, timestamp):
        command, target = data[0], data[1]
        with lock:
            for d in drives:
                if target in (0, d.id):
                    d.on_nmt(command)

    def on_sync(can_id, data, timestamp):
        with lock:
            syncs.append(timestamp)
            streaming = any(d.operational and d.rpdo is not None and d.rpdo.is_received for d in drives)
            if streaming:
                streamed[0] += 1
            if (
                args.fault_after_syncs
                and faulted_at[0] is None
                and streamed[0] >= args.fault_after_syncs
            ):
                drives[args.fault_axis - 1].fault()
                faulted_at[0] = streamed[0]
            for d in drives:
                d.on_sync()

    network.subscribe(0, on_nmt)
    network.subscribe(0x80, on_sync)
    print("ready", flush=True)

    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    done.wait(args.seconds)
    network.disconnect()
    intervals = [b - a for a, b in zip(syncs, syncs[1:])]
    print(json.dumps({
        "drives": [
            {
                "node": d.id,
                "writes": d.writes,
                "controlwords": d.controlwords,
                "targets": d.targets,
                "max_step": d.max_step,
                "max_second": d.max_second,
                "status": d.status,
                "actual": d.actual,
                "lowest": d.lowest,
                "highest": d.highest,
                "max_following": d.max_following,
            }
            for d in drives
        ],
        "syncs": len(syncs),
        "streamed_syncs": streamed[0],
        "faulted_at": faulted_at[0],
        "longest_interval_s": max(intervals) if intervals else 0.0,
    }), flush=True)


if __name__ == "__main__":
    sys.exit(main())
