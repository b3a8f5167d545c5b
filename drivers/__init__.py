"""Device Protocols and the real hardware drivers.

The Protocols (``Hand``, ``HandKinematics``, ``TactileSensor``, ``Camera``) are
here; each driver is in its own module (``dynamixel_hand``, ``optical_tactile``,
``wrist_camera``, ``video``, ``calibration``), which alone imports its hardware
SDK (``dynamixel_sdk``, ``serial``): importing this package loads none.
"""

from tacsplat.drivers.protocols import Camera, Hand, HandKinematics, TactileSensor
from tacsplat.types import TactileReading

__all__ = ["Camera", "Hand", "HandKinematics", "TactileSensor", "TactileReading"]
