"""Exception types shared by every part of tacsplat.

Each error says *what* is at fault (a file and field, a device, a config key, a
tensor) so that one message is enough to fix the input.
"""

from __future__ import annotations

from pathlib import Path


class TacsplatError(Exception):
    """Base class of every error tacsplat raises on purpose."""


class SceneFormatError(TacsplatError):
    """A scene directory (or an imported dataset) is invalid.

    ``path`` is the file at fault and ``field`` the key or record inside it.
    """

    def __init__(self, path: str | Path, field: str | None, message: str):
        self.path = Path(path)
        self.field = field
        super().__init__(f"{self.path}{f' [{field}]' if field else ''}: {message}")


class ConfigError(TacsplatError):
    """A configuration (rig YAML, CLI options, simulation settings) is invalid; names the key."""

    def __init__(self, key: str, message: str, source: str | Path | None = None):
        self.key = key
        self.source = source
        super().__init__(f"{f'{source}: ' if source else ''}{key}: {message}")


class UsageError(ConfigError):
    """A command-line option holds a value out of its range (exit code 2, like argparse's usage errors)."""


class InvalidInputError(TacsplatError, ValueError):
    """A tensor or array argument is invalid (NaN, wrong shape, ...); names the argument."""


class DeviceError(TacsplatError):
    """A device (real or simulated) failed; names the device."""

    def __init__(self, device: str, message: str):
        self.device = device
        super().__init__(f"{device}: {message}")


class HandError(DeviceError):
    """The hand failed: a servo is missing, returned an error, or did not answer."""


class CameraError(DeviceError):
    """A camera failed: could not open, wrong resolution or fps, no frame in time."""


class TactileError(DeviceError):
    """A tactile sensor failed or its calibration is unusable."""


class SimulationError(TacsplatError):
    """The simulation became unstable or was configured with unsafe settings."""


class StorageError(TacsplatError):
    """A file could not be written or read back: the disk is full, the file system is read-only, or the folder
    is not writable. ``path`` is the file (or folder) at fault; nothing written before it is lost."""

    def __init__(self, path: str | Path, reason: str):
        self.path = Path(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")
