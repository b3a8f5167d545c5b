"""Device Protocols and the real hardware drivers.

The Protocols (``Hand``, ``HandKinematics``, ``TactileSensor``, ``Camera``) are here; each driver is in its own
module (``dynamixel_hand``, ``optical_tactile``, ``wrist_camera``, ``video``, ``calibration``), which alone
imports its hardware SDK (``dynamixel_sdk``, of the ``hardware`` extra). The drivers' names resolve here too,
each loading its module on first use, so importing this package loads no SDK::

    from tacsplat.drivers import DynamixelHand, OpticalTactileSensor, WristCamera
"""

from tacsplat.drivers.protocols import Camera, Hand, HandKinematics, TactileSensor
from tacsplat.types import TactileReading

_DRIVERS = ["DynamixelHand", "DynamixelHandConfig", "HandCalibration", "OpticalTactileSensor", "TactileCalibration"]
_DRIVERS += ["WristCamera", "CameraCalibration", "VideoReader"]
__all__ = ["Camera", "Hand", "HandKinematics", "TactileSensor", "TactileReading", *_DRIVERS]


def __getattr__(name: str):
    """A driver's name, imported on first use (static imports, which the layer check reads)."""
    if name in ("DynamixelHand", "DynamixelHandConfig"):
        from tacsplat.drivers import dynamixel_hand as module
    elif name == "HandCalibration":
        from tacsplat.drivers import calibration as module
    elif name in ("OpticalTactileSensor", "TactileCalibration"):
        from tacsplat.drivers import optical_tactile as module
    elif name in ("WristCamera", "CameraCalibration"):
        from tacsplat.drivers import wrist_camera as module
    elif name == "VideoReader":
        from tacsplat.drivers import video as module
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(module, name)


def __dir__() -> list[str]:
    return sorted({*globals(), *_DRIVERS})
