"""Hand calibration file (per-joint sign and offset between servo ticks and joint radians), and the checked
readers of calibration JSON values that the camera calibration uses too.

Motor angle ``theta = (ticks - 2048) * 2 pi / 4096`` (0 at the centre tick);
joint angle ``q = sign * (theta - offset_rad)``, so ``theta = sign * q + offset_rad``.

File (JSON)::

    {"format": "tacsplat-hand-calibration", "version": 1,
     "joints": {"index_0": {"sign": 1, "offset_rad": 0.0}, ...}}

``sign`` is 1 or -1 and ``offset_rad`` a number in [-pi, pi]; every joint of the hand appears once.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from tacsplat.drivers.dynamixel_table import CENTRE_TICK, TICKS_PER_REV
from tacsplat.errors import ConfigError, InvalidInputError
from tacsplat.files import atomic_write

FORMAT = "tacsplat-hand-calibration"
RAD_PER_TICK = 2.0 * math.pi / TICKS_PER_REV
JOINT_FIELDS = ("sign", "offset_rad")


def motor_angles_from_ticks(ticks) -> np.ndarray:
    """Servo ticks -> motor angles in radians, 0 at the centre tick."""
    return (np.asarray(ticks, dtype=np.float64) - CENTRE_TICK) * RAD_PER_TICK


class _RepeatedKey(dict):
    """A JSON object whose text gives a key twice (plain ``json.loads`` keeps the last one silently)."""

    def __init__(self, pairs, repeated: str):
        super().__init__(pairs)
        self.repeated = repeated


def _json_object(pairs: list) -> dict:
    seen = set()
    for key, _ in pairs:
        if key in seen:
            return _RepeatedKey(pairs, key)
        seen.add(key)
    return dict(pairs)


def _repeated_key(value, where: tuple[str, ...] = ()) -> str | None:
    """Dotted path of the first key given twice in one object, or None."""
    if isinstance(value, _RepeatedKey):
        return ".".join(where + (value.repeated,))
    children = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
    for key, child in children:
        found = _repeated_key(child, where + (str(key),))
        if found:
            return found
    return None


def read_calibration_json(path: Path, expected_format: str, version: int = 1) -> dict:
    """A calibration file's JSON object, its ``format``, ``version`` and unique keys checked; errors name the file."""
    try:
        data = json.loads(path.read_text(), object_pairs_hook=_json_object)
    except FileNotFoundError:
        raise ConfigError("calibration", "file not found", source=path) from None
    except OSError as exc:
        raise ConfigError("calibration", f"cannot read the file: {exc}", source=path) from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError("calibration", f"not valid JSON: {exc}", source=path) from None
    repeated = _repeated_key(data)
    if repeated:
        raise ConfigError(repeated, "given twice (the keys of a JSON object must be unique)", source=path)
    if not isinstance(data, dict) or data.get("format") != expected_format:
        raise ConfigError("format", f"expected {expected_format!r}", source=path)
    if not is_json_number(data.get("version")) or data["version"] != version:
        raise ConfigError("version", f"unsupported version {data.get('version')!r} (expected {version})", source=path)
    return data


def is_json_number(value) -> bool:
    """A number, never a boolean (JSON ``true`` is Python's ``True``, an ``int``) nor a string."""
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def json_int(value, key: str, path: Path, minimum: int) -> int:
    """An integer >= ``minimum`` (not a float, not a boolean); ConfigError naming the file and key."""
    if not isinstance(value, int) or isinstance(value, bool) or value < minimum:
        raise ConfigError(key, f"must be an integer >= {minimum}, got {value!r}", source=path)
    return value


def json_float(value, key: str, path: Path, low: float = -math.inf, high: float = math.inf) -> float:
    """A finite number in ``[low, high]``; ConfigError naming the file and key."""
    number = math.nan
    if is_json_number(value):
        try:
            number = float(value)
        except OverflowError:  # an integer literal beyond float64
            number = math.inf
    if not low <= number <= high or not math.isfinite(number):
        raise ConfigError(key, f"must be a finite number in [{low}, {high}], got {value!r}", source=path)
    return number


def json_array(value, key: str, path: Path, shape: tuple[int | None, ...]) -> np.ndarray:
    """Nested JSON lists of finite numbers of this shape (None: any length) as float64; errors name the file and key."""

    def has_shape(v, dims) -> bool:
        if not dims:
            return is_json_number(v)
        return isinstance(v, list) and dims[0] in (None, len(v)) and all(has_shape(x, dims[1:]) for x in v)

    if not has_shape(value, shape):
        what = "a list" if shape == (None,) else "a " + "x".join(str(d) for d in shape) + " array"
        raise ConfigError(key, f"must be {what} of numbers, got {value!r}", source=path)
    with np.errstate(over="ignore"):
        try:
            array = np.array(value, dtype=np.float64)
        except OverflowError:  # an integer literal beyond float64
            array = np.full(np.shape(value), np.inf)
    if not np.all(np.isfinite(array)):
        raise ConfigError(key, f"contains NaN or infinite values: {value!r}", source=path)
    return array


def _sign_problem(sign) -> str | None:
    if not is_json_number(sign) or sign not in (1, -1):
        return f"must be 1 or -1, got {sign!r}"
    return None


def _offset_problem(offset) -> str | None:
    if not is_json_number(offset) or not -math.pi <= offset <= math.pi:
        return f"must be a number of radians in [-pi, pi] (the motor angle at joint zero), got {offset!r}"
    return None


@dataclass(frozen=True)
class HandCalibration:
    """Per-joint sign (+1 or -1) and offset (radians in [-pi, pi]); ``source`` is the file it was read from."""

    joint_names: tuple[str, ...]
    signs: np.ndarray  # [n] +1 or -1
    offsets_rad: np.ndarray  # [n] motor angle at joint zero
    source: str | None = field(default=None, compare=False)

    def __post_init__(self):
        names = tuple(self.joint_names)
        signs, offsets = np.array(self.signs), np.array(self.offsets_rad)
        if len(set(names)) != len(names):
            raise InvalidInputError(f"hand calibration: joint names repeat: {list(names)}")
        if signs.shape != (len(names),) or offsets.shape != (len(names),):
            raise InvalidInputError(
                f"hand calibration: {len(names)} joints need {len(names)} signs and offsets, "
                f"got shapes {signs.shape} and {offsets.shape}"
            )
        for name, sign, offset in zip(names, signs, offsets):
            for what, problem in (("sign", _sign_problem(sign)), ("offset_rad", _offset_problem(offset))):
                if problem:
                    raise InvalidInputError(f"hand calibration: {name}.{what} {problem}")
        object.__setattr__(self, "joint_names", names)
        object.__setattr__(self, "signs", signs.astype(np.float64))
        object.__setattr__(self, "offsets_rad", offsets.astype(np.float64))

    @classmethod
    def identity(cls, joint_names: Sequence[str]) -> "HandCalibration":
        n = len(joint_names)
        return cls(tuple(joint_names), np.ones(n), np.zeros(n))

    def motor_angles(self, q) -> np.ndarray:
        """Joint angles [n] radians -> motor angles [n] radians (``theta = sign * q + offset_rad``)."""
        return self.signs * np.asarray(q, dtype=np.float64) + self.offsets_rad

    def joint_angles(self, theta) -> np.ndarray:
        """Motor angles [n] radians -> joint angles [n] radians."""
        return self.signs * (np.asarray(theta, dtype=np.float64) - self.offsets_rad)

    def ticks_from_radians(self, q) -> np.ndarray:
        """Joint angles [n] radians -> goal ticks [n] int64 (rounded)."""
        return np.rint(self.motor_angles(q) / RAD_PER_TICK + CENTRE_TICK).astype(np.int64)

    def radians_from_ticks(self, ticks) -> np.ndarray:
        """Present ticks [n] -> joint angles [n] radians."""
        return self.joint_angles(motor_angles_from_ticks(ticks))

    def to_json(self) -> dict:
        return {
            "format": FORMAT,
            "version": 1,
            "joints": {
                name: {"sign": int(s), "offset_rad": float(o)}
                for name, s, o in zip(self.joint_names, self.signs, self.offsets_rad)
            },
        }

    def save(self, path: str | Path) -> None:
        atomic_write(path, (json.dumps(self.to_json(), indent=2) + "\n").encode())

    @classmethod
    def load(cls, path: str | Path, joint_names: Sequence[str]) -> "HandCalibration":
        """Read and validate a calibration file for these joints; one ConfigError names the file and field."""
        path = Path(path)
        data = read_calibration_json(path, FORMAT)
        joints = data.get("joints")
        if not isinstance(joints, dict):
            raise ConfigError("joints", "expected an object mapping joint names to {sign, offset_rad}", source=path)
        unknown = [name for name in joints if name not in joint_names]
        if unknown:
            raise ConfigError(f"joints.{unknown[0]}", f"unknown joint (known: {list(joint_names)})", source=path)
        signs, offsets = [], []
        for name in joint_names:
            entry = joints.get(name)
            if not isinstance(entry, dict):
                raise ConfigError(
                    f"joints.{name}", 'missing: expected {"sign": 1 or -1, "offset_rad": radians}', source=path
                )
            extra = [key for key in entry if key not in JOINT_FIELDS]
            if extra:
                raise ConfigError(
                    f"joints.{name}.{extra[0]}", f"unknown field (expected {list(JOINT_FIELDS)})", source=path
                )
            for what, problem in (
                ("sign", _sign_problem(entry.get("sign"))),
                ("offset_rad", _offset_problem(entry.get("offset_rad"))),
            ):
                if problem:
                    raise ConfigError(f"joints.{name}.{what}", problem, source=path)
            signs.append(float(entry["sign"]))
            offsets.append(float(entry["offset_rad"]))
        return cls(tuple(joint_names), np.array(signs), np.array(offsets), source=str(path))

    def check_joints(self, joint_names: Sequence[str]) -> None:
        if tuple(joint_names) != self.joint_names:
            raise InvalidInputError(
                f"hand calibration is for joints {list(self.joint_names)}, the hand has {list(joint_names)}"
            )
