"""A Dynamixel Protocol 2.0 master we did not write, against rigbridge's twin servos:
ROBOTIS' dynamixel-sdk (PyPI `dynamixel-sdk`) pings six servos on the pty given as the
first argument, reads model, firmware and position, switches torque off and on, meets the
EEPROM lock, sync-writes goals 20 ticks over and sync-reads until the servos are there,
then switches torque off. Prints one JSON line. Driven by tests/dynamixel.rs.
"""
import json
import sys
import time

from dynamixel_sdk import (COMM_SUCCESS, GroupSyncRead, GroupSyncWrite, PacketHandler,
                           PortHandler, DXL_HIBYTE, DXL_HIWORD, DXL_LOBYTE, DXL_LOWORD)

IDS = [1, 2, 3, 4, 5, 6]
BAUD = 1_000_000
# X-series control table (XM430-W350 e-manual).
FIRMWARE_VERSION = 6
OPERATING_MODE = 11
TORQUE_ENABLE = 64
GOAL_POSITION = 116
PRESENT_POSITION = 132
RAMP = [1, 2, 3, 4, 4, 3, 2, 1]
CYCLE_S = 0.004
PATIENCE_S = 5.0

port = PortHandler(sys.argv[1])
packets = PacketHandler(2.0)
if not port.openPort() or not port.setBaudRate(BAUD):
    raise SystemExit(f"cannot open {sys.argv[1]}")


def check(what, result, error):
    if result != COMM_SUCCESS:
        raise SystemExit(f"{what}: {packets.getTxRxResult(result)}")
    if error != 0:
        raise SystemExit(f"{what}: {packets.getRxPacketError(error)}")


report = {"models": [], "firmware": [], "start": [], "torque_read": []}
for dxl_id in IDS:
    model, result, error = packets.ping(port, dxl_id)
    check(f"ping {dxl_id}", result, error)
    report["models"].append(model)
    firmware, result, error = packets.read1ByteTxRx(port, dxl_id, FIRMWARE_VERSION)
    check(f"firmware {dxl_id}", result, error)
    report["firmware"].append(firmware)
    check(f"torque off {dxl_id}", *packets.write1ByteTxRx(port, dxl_id, TORQUE_ENABLE, 0))
    position, result, error = packets.read4ByteTxRx(port, dxl_id, PRESENT_POSITION)
    check(f"present {dxl_id}", result, error)
    report["start"].append(position)
    # The goal register may be stale: set it where the servo is before torque comes on.
    check(f"goal {dxl_id}", *packets.write4ByteTxRx(port, dxl_id, GOAL_POSITION, position))
    check(f"torque on {dxl_id}", *packets.write1ByteTxRx(port, dxl_id, TORQUE_ENABLE, 1))
    torque, result, error = packets.read1ByteTxRx(port, dxl_id, TORQUE_ENABLE)
    check(f"torque read {dxl_id}", result, error)
    report["torque_read"].append(torque)

# Operating Mode is EEPROM: locked while torque is on, the servo must answer Access Error.
result, error = packets.write1ByteTxRx(port, IDS[0], OPERATING_MODE, 4)
if result != COMM_SUCCESS:
    raise SystemExit(f"mode write: {packets.getTxRxResult(result)}")
report["eeprom_with_torque_error"] = error & 0x7F

writer = GroupSyncWrite(port, packets, GOAL_POSITION, 4)
reader = GroupSyncRead(port, packets, PRESENT_POSITION, 4)
for dxl_id in IDS:
    if not reader.addParam(dxl_id):
        raise SystemExit(f"sync read param {dxl_id}")


def sync_write(goals):
    writer.clearParam()
    for dxl_id, goal in zip(IDS, goals):
        data = [DXL_LOBYTE(DXL_LOWORD(goal)), DXL_HIBYTE(DXL_LOWORD(goal)),
                DXL_LOBYTE(DXL_HIWORD(goal)), DXL_HIBYTE(DXL_HIWORD(goal))]
        if not writer.addParam(dxl_id, data):
            raise SystemExit(f"sync write param {dxl_id}")
    result = writer.txPacket()
    if result != COMM_SUCCESS:
        raise SystemExit(f"sync write: {packets.getTxRxResult(result)}")


# The goals ramp up and down, one sync write each (the servos judge one a cycle): steps of
# at most 4 ticks (0.35 deg), 1 tick more or less each time, far inside every axis' speed
# and acceleration, 20 ticks in all.
offset = 0
for step in RAMP:
    offset += step
    sync_write([p + offset for p in report["start"]])
    time.sleep(CYCLE_S)
goals = [p + offset for p in report["start"]]
report["goals"] = goals
report["sync_writes"] = len(RAMP)

deadline = time.monotonic() + PATIENCE_S
while True:
    result = reader.txRxPacket()
    if result != COMM_SUCCESS:
        raise SystemExit(f"sync read: {packets.getTxRxResult(result)}")
    present = []
    for dxl_id in IDS:
        if not reader.isAvailable(dxl_id, PRESENT_POSITION, 4):
            raise SystemExit(f"sync read: nothing from {dxl_id}")
        present.append(reader.getData(dxl_id, PRESENT_POSITION, 4))
    if present == goals or time.monotonic() > deadline:
        break
    time.sleep(0.01)
report["final"] = present

for dxl_id in IDS:
    check(f"torque off {dxl_id}", *packets.write1ByteTxRx(port, dxl_id, TORQUE_ENABLE, 0))
port.closePort()
print(json.dumps(report), flush=True)
