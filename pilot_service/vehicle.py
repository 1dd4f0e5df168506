"""ArduSub over MAVLink (pymavlink): heartbeats both ways, the dive mode, arming on request, MANUAL_CONTROL.

ArduSub takes joystick input from the ground station whose system id is its SYSID_MYGCS (255 by default) as
MANUAL_CONTROL: x (surge), y (sway) and r (yaw) from -1000 to 1000, z (heave) from 0 to 1000 with 500 neutral.
It fails safe when the ground station's HEARTBEAT stops, so one is sent every second from a thread of its own.
"""

from __future__ import annotations

import logging
import threading

from pymavlink import mavutil

log = logging.getLogger(__name__)

ARDUSUB_MODES = {"STABILIZE": 0, "ALT_HOLD": 2, "MANUAL": 19}  # ArduSub's custom mode numbers
AXIS_FULL = 1000
HEAVE_NEUTRAL = 500
HEAVE_HALF_RANGE = 500  # z runs from 0 to 1000: full descent to full climb
HEARTBEAT_PERIOD_S = 1.0


class VehicleError(RuntimeError):
    """A vehicle that does not answer or refuses; the message names the endpoint and what to check."""


class Vehicle:
    def __init__(self, endpoint: str, source_system: int = 255, heartbeat_timeout_s: float = 10.0) -> None:
        self.endpoint = endpoint
        self._lock = threading.Lock()  # pymavlink's sender is shared by the heartbeat thread and the control loop
        self._stop = threading.Event()
        try:
            component = mavutil.mavlink.MAV_COMP_ID_MISSIONPLANNER
            self.link = mavutil.mavlink_connection(endpoint, source_system=source_system, source_component=component)
        except Exception as exc:  # pymavlink raises plain socket and serial errors
            raise VehicleError(f"cannot open the MAVLink endpoint {endpoint!r}: {exc}") from None
        self._heartbeats = threading.Thread(target=self._send_heartbeats, name="gcs-heartbeat", daemon=True)
        self._heartbeats.start()
        heartbeat = self.link.wait_heartbeat(timeout=heartbeat_timeout_s)
        if heartbeat is None:
            self.close()
            raise VehicleError(f"no HEARTBEAT from a vehicle on {endpoint} within {heartbeat_timeout_s:g} s: is the "
                               "rover (BlueOS's MAVLink endpoint) up, and does it send to this address?")  # fmt: skip
        self.target_system, self.target_component = heartbeat.get_srcSystem(), heartbeat.get_srcComponent()
        log.info("vehicle %d on %s (autopilot %d, type %d)", self.target_system, endpoint, heartbeat.autopilot,
                 heartbeat.type)  # fmt: skip

    def _send_heartbeats(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                self.link.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_AUTOPILOT_INVALID,
                                             0, 0, mavutil.mavlink.MAV_STATE_ACTIVE)  # fmt: skip
            self._stop.wait(HEARTBEAT_PERIOD_S)

    def set_mode(self, name: str) -> None:
        with self._lock:
            self.link.mav.set_mode_send(self.target_system, mavutil.mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                                        ARDUSUB_MODES[name])  # fmt: skip
        log.info("asked for mode %s", name)

    def arm(self) -> None:
        with self._lock:
            arm = mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM
            self.link.mav.command_long_send(self.target_system, self.target_component, arm, 0, 1, 0, 0, 0, 0, 0, 0)
        log.warning("asked the vehicle to ARM")

    def send_control(self, surge: float, yaw: float, heave: float = 0.0) -> tuple[int, int, int, int]:
        """MANUAL_CONTROL of surge, yaw and heave in [-1, 1] (sway 0; heave 0 is neutral: in ALT_HOLD, depth held);
        returns x, y, z, r."""
        x, z, r = round(surge * AXIS_FULL), HEAVE_NEUTRAL + round(heave * HEAVE_HALF_RANGE), round(yaw * AXIS_FULL)
        with self._lock:
            self.link.mav.manual_control_send(self.target_system, x, 0, z, r, 0)
        return x, 0, z, r

    def close(self) -> None:
        self._stop.set()
        self._heartbeats.join(timeout=2 * HEARTBEAT_PERIOD_S)
        self.link.close()
