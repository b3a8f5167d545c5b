"""Hand calibration file: per-joint sign and offset between servo ticks and joint radians.

Motor angle ``theta = (ticks - 2048) * 2 pi / 4096`` (0 at the centre tick);
joint angle ``q = sign * (theta - offset_rad)``, so ``theta = sign * q + offset_rad``.

File (JSON)::

    {"format": "tacsplat-hand-calibration", "version": 1,
     "joints": {"index_0": {"sign": 1, "offset_rad": 0.0}, ...}}
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from tacsplat.drivers.dynamixel_table import CENTRE_TICK, TICKS_PER_REV
from tacsplat.errors import ConfigError, InvalidInputError

FORMAT = "tacsplat-hand-calibration"


def read_calibration_json(path: Path, expected_format: str) -> dict:
    """A calibration file's JSON object, checked for its ``format`` tag; errors name the file."""
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError("calibration", "file not found", source=path) from None
    except json.JSONDecodeError as exc:
        raise ConfigError("calibration", f"not valid JSON: {exc}", source=path) from None
    if not isinstance(data, dict) or data.get("format") != expected_format:
        raise ConfigError("format", f"expected {expected_format!r}", source=path)
    return data
RAD_PER_TICK = 2.0 * math.pi / TICKS_PER_REV


@dataclass(frozen=True)
class HandCalibration:
    joint_names: tuple[str, ...]
    signs: np.ndarray  # [n] +1 or -1
    offsets_rad: np.ndarray  # [n] motor angle at joint zero

    @classmethod
    def identity(cls, joint_names: Sequence[str]) -> "HandCalibration":
        n = len(joint_names)
        return cls(tuple(joint_names), np.ones(n), np.zeros(n))

    def ticks_from_radians(self, q) -> np.ndarray:
        """Joint angles [n] radians -> goal ticks [n] int64 (rounded)."""
        theta = self.signs * np.asarray(q, dtype=np.float64) + self.offsets_rad
        return np.rint(theta / RAD_PER_TICK + CENTRE_TICK).astype(np.int64)

    def radians_from_ticks(self, ticks) -> np.ndarray:
        """Present ticks [n] -> joint angles [n] radians."""
        theta = (np.asarray(ticks, dtype=np.float64) - CENTRE_TICK) * RAD_PER_TICK
        return self.signs * (theta - self.offsets_rad)

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
        path = Path(path)
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_text(json.dumps(self.to_json(), indent=2) + "\n")
        tmp.replace(path)

    @classmethod
    def load(cls, path: str | Path, joint_names: Sequence[str]) -> "HandCalibration":
        """Read and validate a calibration file for these joints; errors name the file and key."""
        path = Path(path)
        data = read_calibration_json(path, FORMAT)
        if data.get("version") != 1:
            raise ConfigError("version", f"unsupported version {data.get('version')!r}", source=path)
        joints = data.get("joints")
        if not isinstance(joints, dict):
            raise ConfigError("joints", "expected an object mapping joint names to {sign, offset_rad}", source=path)
        unknown = sorted(set(joints) - set(joint_names))
        if unknown:
            raise ConfigError(f"joints.{unknown[0]}", f"unknown joint (known: {list(joint_names)})", source=path)
        signs, offsets = [], []
        for name in joint_names:
            entry = joints.get(name)
            if not isinstance(entry, dict):
                raise ConfigError(f"joints.{name}", "missing", source=path)
            sign, offset = entry.get("sign"), entry.get("offset_rad")
            if sign not in (1, -1):
                raise ConfigError(f"joints.{name}.sign", f"must be 1 or -1, got {sign!r}", source=path)
            if not isinstance(offset, (int, float)) or not math.isfinite(offset):
                raise ConfigError(f"joints.{name}.offset_rad", f"must be a finite number, got {offset!r}", source=path)
            signs.append(float(sign))
            offsets.append(float(offset))
        return cls(tuple(joint_names), np.array(signs), np.array(offsets))

    def check_joints(self, joint_names: Sequence[str]) -> None:
        if tuple(joint_names) != self.joint_names:
            raise InvalidInputError(
                f"hand calibration is for joints {list(self.joint_names)}, the hand has {list(joint_names)}"
            )
