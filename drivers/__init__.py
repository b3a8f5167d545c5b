"""Device Protocols and the real hardware drivers.

Hardware SDKs (``dynamixel_sdk``, ``serial``) are imported only inside the
driver modules that need them, never here at import time: the drivers below
are loaded on first use (``from tacsplat.drivers import DynamixelHand``).
"""

from importlib import import_module

from tacsplat.drivers.protocols import Camera, Hand, TactileSensor
from tacsplat.types import TactileReading

_LAZY = {
    "DynamixelHand": "tacsplat.drivers.dynamixel_hand",
    "DynamixelHandConfig": "tacsplat.drivers.dynamixel_hand",
    "ServoError": "tacsplat.drivers.dynamixel_hand",
    "HandCalibration": "tacsplat.drivers.calibration",
    "OpticalTactileSensor": "tacsplat.drivers.optical_tactile",
    "TactileCalibration": "tacsplat.drivers.optical_tactile",
    "WristCamera": "tacsplat.drivers.wrist_camera",
    "CameraCalibration": "tacsplat.drivers.wrist_camera",
    "VideoReader": "tacsplat.drivers.video",
}

__all__ = ["Camera", "Hand", "TactileSensor", "TactileReading", *_LAZY]


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'tacsplat.drivers' has no attribute {name!r}")
