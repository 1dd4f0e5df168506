"""A stand-in for ArduSub in its own process: HEARTBEATs as a submarine, and every message a ground station sends
written to a JSON-lines file as it arrives (time, message name "msg", fields).

    python fake_vehicle.py ENDPOINT OUT
"""

from __future__ import annotations

import json
import sys
import time

from pymavlink import mavutil


def main(endpoint: str, out: str) -> None:
    link = mavutil.mavlink_connection(endpoint, source_system=1, source_component=1)
    next_heartbeat = 0.0
    with open(out, "w") as log:
        while True:
            now = time.monotonic()
            if now >= next_heartbeat:
                link.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_SUBMARINE, mavutil.mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                        0, 0, mavutil.mavlink.MAV_STATE_STANDBY)  # fmt: skip
                next_heartbeat = now + 0.5
            message = link.recv_match(blocking=True, timeout=0.05)
            if message is not None and message.get_type() != "BAD_DATA":
                fields = {key: value for key, value in message.to_dict().items() if key != "mavpackettype"}
                log.write(json.dumps({"t": time.time(), "msg": message.get_type(), "src": message.get_srcSystem(),
                                      **fields}) + "\n")  # fmt: skip
                log.flush()


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
