"""Device Protocols and the real hardware drivers.

Hardware SDKs (``dynamixel_sdk``, ``serial``) are imported only inside the
driver modules that need them, never here at import time.
"""

from tacsplat.drivers.protocols import Camera, Hand, TactileSensor
from tacsplat.types import TactileReading

__all__ = ["Camera", "Hand", "TactileSensor", "TactileReading"]
