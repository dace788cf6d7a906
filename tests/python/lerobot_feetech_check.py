"""LeRobot's Feetech driver against a served bus (run by lerobot-feetech-check.sh).

    lerobot_feetech_check.py DEVICE --motors ID:MODEL,... [--alone ID]

Connects `FeetechMotorsBus` as LeRobot does (its handshake pings every id, compares the model
number and checks that every servo has the same firmware), reads and sync-reads positions,
writes the goal each servo already has, and asks for the broadcast ping and `scan_port`. Prints
one JSON object: each check's result, or the error it raised. With `--alone ID` only that servo
answers on the bus (the others powered off): the broadcast ping must find it alone, at its rate.
Without it, several servos answer the broadcast ping at once, as on a real bus: LeRobot's parser
gets garbled bytes and returns None, which is what the check expects.
"""

import argparse
import json
import pathlib
import sys
import types

import lerobot

# lerobot/utils/__init__.py imports torch and huggingface_hub; the modules the motors package
# needs from it (import_utils, decorators, utils, errors) do not. Registering the package
# without running its __init__ lets them import alone.
_utils = types.ModuleType("lerobot.utils")
_utils.__path__ = [str(pathlib.Path(lerobot.__file__).parent / "utils")]
sys.modules["lerobot.utils"] = _utils
lerobot.utils = _utils

from lerobot.motors import Motor, MotorNormMode  # noqa: E402
from lerobot.motors.feetech import FeetechMotorsBus  # noqa: E402
import lerobot.motors.feetech.tables as tables  # noqa: E402

# The STS3095 (model number 2569) shares the STS3215's control table, resolution and rates;
# lerobot 0.6.1 does not list it. The class copies the tables when it is defined.
if "sts3095" not in FeetechMotorsBus.model_number_table:
    bus_class = FeetechMotorsBus
    bus_class.model_number_table["sts3095"] = 2569
    for table in ("model_ctrl_table", "model_resolution_table", "model_baudrate_table",
                  "model_encoding_table"):
        getattr(bus_class, table)["sts3095"] = getattr(bus_class, table)["sts3215"]
    tables.MODEL_PROTOCOL["sts3095"] = tables.MODEL_PROTOCOL["sts3215"]


def attempt(results, name, f):
    try:
        results[name] = {"ok": f()}
    except Exception as e:  # noqa: BLE001 - each check's failure is reported, not raised
        results[name] = {"error": f"{type(e).__name__}: {e}"}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("device")
    ap.add_argument("--motors", required=True, help="ID:MODEL,... in joint order")
    ap.add_argument("--alone", type=int, help="the one servo powered")
    args = ap.parse_args()
    motors = {}
    for item in args.motors.split(","):
        motor_id, model = item.split(":")
        motors[f"m{motor_id}"] = Motor(int(motor_id), model, MotorNormMode.RANGE_M100_100)
    if args.alone is not None:
        motors = {k: m for k, m in motors.items() if m.id == args.alone}
    results = {"lerobot": lerobot.__version__}
    bus = FeetechMotorsBus(port=args.device, motors=motors)
    attempt(results, "connect", lambda: bus.connect() or True)
    if bus.is_connected:
        names = list(motors)
        attempt(results, "ping", lambda: {n: bus.ping(n) for n in names})
        attempt(results, "firmware", lambda: bus._read_firmware_version(bus.ids))
        attempt(results, "read", lambda: {n: bus.read("Present_Position", n, normalize=False)
                                          for n in names})
        attempt(results, "sync_read", lambda: bus.sync_read("Present_Position", normalize=False))
        attempt(results, "return_delay",
                lambda: bus.sync_read("Return_Delay_Time", normalize=False))

        def hold_where_they_are():
            goals = bus.sync_read("Present_Position", normalize=False)
            bus.sync_write("Goal_Position", goals, normalize=False)
            return goals

        attempt(results, "sync_write", hold_where_they_are)
        attempt(results, "broadcast_ping", lambda: bus.broadcast_ping())
        bus.disconnect(disable_torque=False)
    attempt(results, "scan_port", lambda: {str(baud): ids for baud, ids in
                                           FeetechMotorsBus.scan_port(args.device).items()})
    print(json.dumps(results))


if __name__ == "__main__":
    main()
