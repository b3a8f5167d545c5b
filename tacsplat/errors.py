"""Exception types shared by every part of tacsplat.

Each error says *what* is at fault (a file and field, a device, a config key, a
tensor) so that one message is enough to fix the input.
"""

from __future__ import annotations

from collections.abc import Callable
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


def pydantic_problem(
    error,
    word: str = "field",
    prefix: str = "",
    unknown: Callable[[tuple], str | None] | None = None,
    expected: dict[str, str] | None = None,
) -> tuple[str, str]:
    """pydantic's first error (a ValidationError, or one entry of its ``errors()``) as (the field's path after
    ``prefix``: ``presses[0].file``; what is wrong). ``word`` names a field ("key" in a YAML), ``unknown(loc)`` notes
    what may stand at an unknown one's place, ``expected`` says what each kind of error (by its first word: ``int``)
    expects."""
    if not isinstance(error, dict):
        error = error.errors(include_url=False)[0]
    loc, kind = error["loc"], error["type"]

    def path(loc: tuple) -> str:  # a mapping's key ("[key]") is named by the key itself
        key = "".join(f"[{part}]" if isinstance(part, int) else f".{part}" for part in loc if part != "[key]")
        return (prefix + key.removeprefix(".")) or "(top level)"

    if kind in ("extra_forbidden", "unexpected_keyword_argument"):  # a model's, a dataclass's
        note = unknown(loc) if unknown else None
        return path(loc), f"unknown {word}" + (f" ({note})" if note else "")
    if kind == "missing" and isinstance(loc[-1], int):  # a fixed-length list that is too short
        return path(loc[:-1]), f"expected a list of more than {loc[-1]} values"
    if kind == "missing":
        return path(loc), f"missing (a required {word})"
    if expected and kind.split("_")[0] in expected:
        return path(loc), f"expected {expected[kind.split('_')[0]]}, got {error['input']!r}"
    if kind == "value_error":  # a validator's own message
        return path(loc), str(error["ctx"]["error"])
    return path(loc), f"{error['msg']}, got {error.get('input')!r}"
