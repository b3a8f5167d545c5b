"""Hand calibration file (per-joint sign and offset between servo ticks and joint radians), and the reader of
calibration files (JSON, checked by pydantic models: :mod:`tacsplat.drivers.calibration_files`) that the other
calibration files use too.

Motor angle ``theta = (ticks - 2048) * 2 pi / 4096`` (0 at the centre tick);
joint angle ``q = sign * (theta - offset_rad)``, so ``theta = sign * q + offset_rad``.

A joint's range must lie within one turn of its servo, ticks 0..4095 (motor angles [-pi, pi)): an X-series servo
reads its position within one turn after power-on, so a range across the 4095/0 tick seam would read a turn off
wherever the finger rests on the far side (:func:`seam_crossing`; ``calibrate hand`` refuses such a joint).

File (JSON)::

    {"format": "tacsplat-hand-calibration", "version": 1,
     "joints": {"index_0": {"sign": 1, "offset_rad": 0.0}, ...}}

``sign`` is 1 or -1 and ``offset_rad`` a number in [-pi, pi]; every joint of the hand appears once.
"""

from __future__ import annotations

import functools
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Sequence, TypeVar

import numpy as np

from tacsplat.drivers.dynamixel_table import CENTRE_TICK, TICKS_PER_REV
from tacsplat.errors import ConfigError, InvalidInputError, pydantic_problem
from tacsplat.files import atomic_write
from tacsplat.geometry import rigidity_problem

FORMAT = "tacsplat-hand-calibration"
RAD_PER_TICK = 2.0 * math.pi / TICKS_PER_REV
JOINT_FIELDS = ("sign", "offset_rad")
# the most a driver's connect and reading tolerances may be: how far outside its limits a joint may read, so
# ``calibrate hand`` keeps every joint's range at least this far from the seam
MAX_TOLERANCE_RAD = 0.2
T = TypeVar("T")


def motor_angles_from_ticks(ticks) -> np.ndarray:
    """Servo ticks -> motor angles in radians, 0 at the centre tick."""
    return (np.asarray(ticks, dtype=np.float64) - CENTRE_TICK) * RAD_PER_TICK


def seam_crossing(sign: float, offset_rad: float, lower: float, upper: float, margin_rad: float = 0.0):
    """``(lowest, highest)`` tick of the motor over the joint range [``lower``, ``upper``] widened by ``margin_rad`` at
    each end, with this sign and offset, when they leave one turn (ticks 0..4095: the range crosses the 4095/0 seam,
    where the servo's one-turn reading after power-on jumps by a turn); None when the range lies within it."""
    ends = [(sign * q + offset_rad) / RAD_PER_TICK + CENTRE_TICK for q in (lower - margin_rad, upper + margin_rad)]
    low, high = min(ends), max(ends)
    return None if low >= 0 and high <= TICKS_PER_REV - 1 else (int(math.floor(low)), int(math.ceil(high)))


def seam_advice(name: str) -> str:
    """What to do about joint ``name``'s range crossing its servo's tick seam."""
    return (
        f"re-seat {name}'s servo horn (or set the servo's Homing Offset) so that the joint's whole range lies within "
        "one turn, ticks 0..4095 (joint zero near the centre tick 2048), then run `tacsplat calibrate hand` again"
    )


class _RepeatedKey(dict):
    """A JSON object whose text gives a key twice (plain ``json.loads`` keeps the last one silently)."""

    def __init__(self, pairs, repeated: str):
        super().__init__(pairs)
        self.repeated = repeated


def _json_object(pairs: list) -> dict:
    keys = [key for key, _ in pairs]
    repeated = next((key for i, key in enumerate(keys) if key in keys[:i]), None)
    return dict(pairs) if repeated is None else _RepeatedKey(pairs, repeated)


def _repeated_key(value, where: tuple[str, ...] = ()) -> str | None:
    """Dotted path of the first key given twice in one object, or None."""
    if isinstance(value, _RepeatedKey):
        return ".".join(where + (value.repeated,))
    children = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
    for key, child in children:
        if found := _repeated_key(child, where + (str(key),)):
            return found
    return None


def read_calibration(
    path: Path, model: type[T], expected_format: str | None = None, version: int = 1, key: str = "calibration"
) -> T:
    """A JSON file's object as ``model`` (its keys unique, its ``format`` and ``version`` checked when
    ``expected_format`` is given, then every other field by pydantic, strictly); one ConfigError names the file and
    the field (``key`` when the file cannot be read)."""
    try:
        data = json.loads(path.read_text(), object_pairs_hook=_json_object)
    except FileNotFoundError:
        raise ConfigError(key, "file not found", source=path) from None
    except OSError as exc:
        raise ConfigError(key, f"cannot read the file: {exc}", source=path) from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(key, f"not valid JSON: {exc}", source=path) from None
    if repeated := _repeated_key(data):
        raise ConfigError(repeated, "given twice (the keys of a JSON object must be unique)", source=path)
    if expected_format is not None:
        if not isinstance(data, dict) or data.get("format") != expected_format:
            raise ConfigError("format", f"expected {expected_format!r}", source=path)
        if not is_json_number(data.get("version")) or data["version"] != version:
            raise ConfigError(
                "version", f"unsupported version {data.get('version')!r} (expected {version})", source=path
            )
        data = {k: v for k, v in data.items() if k not in ("format", "version")}
    from pydantic import ValidationError

    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(*field_error(exc, model), source=path) from None


def field_error(exc, model) -> tuple[str, str]:
    """pydantic's first error (a ValidationError of ``model``) as (the field's path, ``presses[0].file``; what is
    wrong)."""
    fields = list(model.model_fields)
    return pydantic_problem(
        exc, unknown=lambda loc: f"expected {fields}" if len(loc) == 1 else None, expected={"model": "a JSON object"}
    )


def json_array(shape: tuple[int | None, ...], value) -> np.ndarray:
    """Nested JSON lists of finite numbers of this shape (None: any length) as float64."""

    def has_shape(v, dims) -> bool:
        if not dims:
            return is_json_number(v)
        return isinstance(v, list) and dims[0] in (None, len(v)) and all(has_shape(x, dims[1:]) for x in v)

    if not has_shape(value, shape):
        what = "a list" if shape == (None,) else "a " + "x".join(str(d) for d in shape) + " array"
        raise ValueError(f"must be {what} of numbers, got {value!r}")
    with np.errstate(over="ignore"):
        try:
            array = np.array(value, dtype=np.float64)
        except OverflowError:  # an integer literal beyond float64
            array = np.full(np.shape(value), np.inf)
    if not np.all(np.isfinite(array)):
        raise ValueError(f"contains NaN or infinite values: {value!r}")
    return array


def json_rigid(value) -> np.ndarray:
    T = json_array((4, 4), value)
    if problem := rigidity_problem(T):
        raise ValueError(f"not a rigid transform: {problem}")
    return T


def _sign_problem(sign) -> str | None:
    return None if is_json_number(sign) and sign in (1, -1) else f"must be 1 or -1, got {sign!r}"


def _offset_problem(offset) -> str | None:
    if not is_json_number(offset) or not -math.pi <= offset <= math.pi:
        return f"must be a number of radians in [-pi, pi] (the motor angle at joint zero), got {offset!r}"
    return None


def is_json_number(value) -> bool:
    """A number, never a boolean (JSON ``true`` is Python's ``True``, an ``int``) nor a string."""
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


@functools.cache
def _hand_file():
    """The pydantic model of a hand calibration file, built on first use (the hand's guard process, which imports
    this module, starts without pydantic)."""
    from pydantic import BaseModel, ConfigDict, PlainValidator

    def checked(problem):
        """A field that ``problem(value)`` (a message or None) checks."""

        def validate(value):
            if message := problem(value):
                raise ValueError(message)
            return float(value)

        return Annotated[Any, PlainValidator(validate)]

    class Joint(BaseModel):
        model_config = ConfigDict(strict=True, extra="forbid")
        sign: checked(_sign_problem)
        offset_rad: checked(_offset_problem)

    class HandFile(BaseModel):
        model_config = ConfigDict(strict=True, extra="forbid")
        joints: dict[str, Joint]

    return HandFile


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

    def save(self, path: str | Path) -> None:
        values = zip(self.signs, self.offsets_rad)
        joints = {n: {"sign": int(s), "offset_rad": float(o)} for n, (s, o) in zip(self.joint_names, values)}
        data = {"format": FORMAT, "version": 1, "joints": joints}
        atomic_write(path, (json.dumps(data, indent=2) + "\n").encode())

    @classmethod
    def load(cls, path: str | Path, joint_names: Sequence[str]) -> "HandCalibration":
        """Read and validate a calibration file for these joints; one ConfigError names the file and field."""
        path = Path(path)
        joints = read_calibration(path, _hand_file(), FORMAT).joints
        if unknown := [name for name in joints if name not in joint_names]:
            raise ConfigError(f"joints.{unknown[0]}", f"unknown joint (known: {list(joint_names)})", source=path)
        if missing := [name for name in joint_names if name not in joints]:
            raise ConfigError(
                f"joints.{missing[0]}", 'missing: expected {"sign": 1 or -1, "offset_rad": radians}', source=path
            )
        signs, offsets = ([getattr(joints[name], key) for name in joint_names] for key in JOINT_FIELDS)
        return cls(tuple(joint_names), np.array(signs), np.array(offsets), source=str(path))

    def check_joints(self, joint_names: Sequence[str]) -> None:
        if tuple(joint_names) != self.joint_names:
            raise InvalidInputError(
                f"hand calibration is for joints {list(self.joint_names)}, the hand has {list(joint_names)}"
            )
