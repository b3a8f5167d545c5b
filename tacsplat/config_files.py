"""What the YAML settings files share (the rig file, ``reconstruct --config``): how a number YAML left as a string is
read."""

from __future__ import annotations

import math
import types
from typing import Union, get_args, get_origin


def field_kinds(kind) -> tuple:
    """The types a field of type ``kind`` holds: a union's members (``float | None``, ``Optional[float]``), else
    ``kind`` alone."""
    return get_args(kind) if isinstance(kind, types.UnionType) or get_origin(kind) is Union else (kind,)


def yaml_number(text: str, kind) -> object:
    """The number ``text`` spells, for a field of type ``kind`` that holds an int or a float and no string: YAML 1.1
    reads a number written without a dot (``1e-3``) as a string. An int field takes a whole number only (``1e3`` is
    1000). ``text`` itself otherwise (a word, NaN, infinity, or a field that holds strings), for the field's own check
    to refuse."""
    kinds = field_kinds(kind)
    if str in kinds or not {int, float} & set(kinds):
        return text
    try:
        number = float(text)
    except ValueError:
        return text
    if not math.isfinite(number):
        return text
    if float not in kinds:
        return int(number) if number.is_integer() else text
    return number
