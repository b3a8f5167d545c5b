"""Device Protocols and the real hardware drivers.

The Protocols (``Hand``, ``HandKinematics``, ``TactileSensor``, ``Camera``) are here; each driver is in its own
module (``dynamixel_hand``, ``optical_tactile``, ``wrist_camera``, ``video``, ``calibration``), which alone
imports its hardware SDK (``dynamixel_sdk``, of the ``hardware`` extra). The drivers' names resolve here too,
each loading its module on first use, so importing this package loads no SDK::

    from tacsplat.drivers import DynamixelHand, OpticalTactileSensor, WristCamera
"""

import importlib

from tacsplat.drivers.protocols import Camera, Hand, HandKinematics, TactileSensor
from tacsplat.types import TactileReading

_DRIVERS = {  # name -> the module that defines it
    "DynamixelHand": "tacsplat.drivers.dynamixel_hand",
    "DynamixelHandConfig": "tacsplat.drivers.dynamixel_hand",
    "HandCalibration": "tacsplat.drivers.calibration",
    "OpticalTactileSensor": "tacsplat.drivers.optical_tactile",
    "TactileCalibration": "tacsplat.drivers.optical_tactile",
    "WristCamera": "tacsplat.drivers.wrist_camera",
    "CameraCalibration": "tacsplat.drivers.wrist_camera",
    "VideoReader": "tacsplat.drivers.video",
}
__all__ = ["Camera", "Hand", "HandKinematics", "TactileSensor", "TactileReading", *_DRIVERS]


def __getattr__(name: str):
    if name not in _DRIVERS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(_DRIVERS[name]), name)


def __dir__() -> list[str]:
    return sorted({*globals(), *_DRIVERS})
