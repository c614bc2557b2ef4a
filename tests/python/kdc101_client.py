"""Drives a KDC101 on a serial port with thorlabs-apt-device, as a lab's
script would, and prints what it saw as one JSON object.

Usage: kdc101_client.py PORT AUTO_PORT (two controllers: the second is
only ever driven with status updates the controller sends by itself)
"""

import json
import sys
import time

from thorlabs_apt_device import KDC101
from thorlabs_apt_device.devices.aptdevice_motor import APTDevice_Motor
from thorlabs_apt_device.enums import EndPoint

COUNTS_PER_MM = 34554.96
VELOCITY_PER_MM_S = 772981  # device units per mm/s (KDC101, Z8)


def wait(predicate, timeout=15.0):
    start = time.time()
    while time.time() - start < timeout:
        if predicate():
            return True
        time.sleep(0.02)
    return False


def still(status):
    return not any(
        status[k] for k in ("moving_forward", "moving_reverse", "jogging_forward", "jogging_reverse")
    )


def main(port, auto_port):
    seen = {}
    stage = KDC101(serial_port=port, home=False)
    status = stage.status
    stage.identify()
    stage.set_velocity_params(acceleration=2 * 264, max_velocity=2 * VELOCITY_PER_MM_S)
    stage.set_home_params(velocity=2 * VELOCITY_PER_MM_S, offset_distance=int(0.5 * COUNTS_PER_MM))
    stage.set_jog_params(size=int(0.25 * COUNTS_PER_MM), acceleration=2 * 264, max_velocity=VELOCITY_PER_MM_S)
    stage.set_enabled(True)
    time.sleep(0.5)
    seen["velparams"] = stage.velparams["max_velocity"]
    seen["homeparams"] = [stage.homeparams["home_velocity"], stage.homeparams["offset_distance"]]
    seen["jogparams"] = stage.jogparams["step_size"]
    seen["enabled"] = status["channel_enabled"]

    stage.home()
    seen["homed"] = wait(lambda: status["homed"] and not status["homing"] and still(status))
    seen["after_home"] = status["position"]

    target = int(2.0 * COUNTS_PER_MM)
    stage.move_absolute(target)
    seen["absolute"] = wait(lambda: abs(status["position"] - target) <= 2 and still(status))
    seen["at_absolute"] = status["position"]

    stage.move_relative(-int(0.5 * COUNTS_PER_MM))
    target -= int(0.5 * COUNTS_PER_MM)
    seen["relative"] = wait(lambda: abs(status["position"] - target) <= 2 and still(status))
    seen["at_relative"] = status["position"]

    stage.move_jog("forward")
    time.sleep(0.05)
    seen["jog"] = wait(lambda: abs(abs(status["position"] - target) - int(0.25 * COUNTS_PER_MM)) <= 2 and still(status))
    seen["after_jog"] = status["position"]

    def velocity_move(direction, settle):
        """[position, velocity, position 0.3 s later] once moving."""
        stage.move_velocity(direction)
        time.sleep(settle)
        before, velocity = status["position"], status["velocity"]
        time.sleep(0.3)
        return [before, velocity, status["position"]]

    seen["velocity_moving"] = velocity_move("forward", 0.6)
    seen["velocity_reversed"] = velocity_move("reverse", 1.2)
    stage.stop(immediate=True)
    seen["stopped"] = wait(lambda: still(status) and status["velocity"] == 0)
    stage.close()

    # Status updates the controller sends by itself (HW_START_UPDATEMSGS):
    # nothing polls here, so only they can move the position.
    auto = APTDevice_Motor(
        serial_port=auto_port,
        status_updates="auto",
        controller=EndPoint.USB,
        bays=(EndPoint.USB,),
        channels=(1,),
        home=False,
    )
    # The library's reader hands its thread back to queued commands only
    # when a read times out, after 0.1 s: the controller's update period.
    # Over USB a KDC101's updates reach the host in the 16 ms ticks of its
    # FTDI chip's latency timer, so reads time out now and then; on the
    # twin's pseudo-terminal they come every 100 ms, and the move below
    # waited over 15 s in about one run in five.
    auto._port.timeout = 0.05
    auto.set_enabled(True)
    auto.set_velocity_params(acceleration=2 * 264, max_velocity=VELOCITY_PER_MM_S)
    moving = auto.status_[0][0]
    # The library asks for updates 0.25 s after opening the port; until the
    # first arrives its position is a placeholder 0 (the simulated motor
    # starts 6 mm from the reverse limit, so no real reading is 0).
    seen["first_update"] = wait(lambda: moving["position"] != 0)
    start, target = moving["position"], int(3.0 * COUNTS_PER_MM)
    auto.move_absolute(target)
    # A position on the way: no MOVE_COMPLETED carries one.
    lo, hi = min(start, target) + 1000, max(start, target) - 1000
    seen["auto_updates"] = wait(lambda: lo < moving["position"] < hi)
    auto.close()
    print(json.dumps(seen))


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
