"""The pydantic base and field types of the calibration files, which :func:`tacsplat.drivers.calibration.read_calibration`
reads: strict types (no string for a number, no boolean for a number), unknown fields refused, arrays of finite
numbers of a shape, rigid transforms."""

from __future__ import annotations

import functools
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, PlainValidator

from tacsplat.drivers.calibration import json_array, json_rigid


class CalibrationFile(BaseModel):
    """The fields of a calibration file but ``format`` and ``version``."""

    model_config = ConfigDict(strict=True, extra="forbid")


def Array(*shape: int | None):
    """A field of nested JSON lists of finite numbers of this shape (None: any length), read as float64."""
    return Annotated[Any, PlainValidator(functools.partial(json_array, shape))]


Rigid = Annotated[Any, PlainValidator(json_rigid)]  # a rigid 4x4 transform
NonNegative = Annotated[float, Field(allow_inf_nan=False, ge=0.0)]
