"""Command-line options generated from a config dataclass: one flag per field, documented where the field is.

Each field of :class:`~tacsplat.reconstruction.config.TrainConfig` (and of its
nested dataclasses, with their name as a prefix) becomes ``--field-name``; its
help is the comment written beside the field, and the default shown is the
field's default, so the code is the one source of truth. A comment line
``# -- title`` inside the class starts an argument group. Booleans become
``--name/--no-name`` (``use_touch`` -> ``--touch/--no-touch``), ``Literal``
fields get their choices, ``X | None`` fields accept ``none``.
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import io
import textwrap
import tokenize
import typing
from dataclasses import dataclass


@dataclass(frozen=True)
class FieldOption:
    path: tuple[str, ...]  # field names from the top config down, e.g. ("densify", "max_gaussians")
    flag: str  # e.g. "--densify-max-gaussians"
    dest: str  # the argparse destination


def field_docs(cls) -> tuple[dict[str, str], dict[str, str]]:
    """``({field: comment}, {field: group title})`` read from the class's source comments."""
    source = textwrap.dedent(inspect.getsource(cls))
    docs: dict[str, str] = {}
    groups: dict[str, str] = {}
    current_field, current_group = None, ""
    lines = source.splitlines()
    comments = {tok.start[0]: tok.string for tok in tokenize.generate_tokens(io.StringIO(source).readline)
                if tok.type == tokenize.COMMENT}
    names = {f.name for f in dataclasses.fields(cls)}
    for number, line in enumerate(lines, start=1):
        stripped = line.strip()
        comment = comments.get(number, "")
        text = comment.lstrip("#").strip()
        if stripped.startswith("#"):
            if text.startswith("--"):
                current_group, current_field = text.lstrip("-").strip(), None
            elif current_field is not None:
                docs[current_field] += " " + text
            continue
        head = stripped.split(":", 1)[0].strip()
        if head in names and ":" in stripped:
            current_field = head
            docs[head] = text
            groups[head] = current_group
        else:
            current_field = None
    return docs, groups


def _flag_name(name: str) -> str:
    return (name[4:] if name.startswith("use_") else name).replace("_", "-")


def _none_or(kind):
    def parse(text: str):
        return None if text.lower() == "none" else kind(text)

    parse.__name__ = kind.__name__
    return parse


def add_config_options(parser: argparse.ArgumentParser, cls, prefix: tuple[str, ...] = (),
                       skip: set[str] = frozenset()) -> list[FieldOption]:
    """Add one option per field of dataclass ``cls`` (recursing into nested dataclasses); returns them.

    Options default to ``argparse.SUPPRESS``: only the ones given appear in the parsed namespace.
    """
    hints = typing.get_type_hints(cls)
    docs, groups = field_docs(cls)
    defaults = cls()
    added: list[FieldOption] = []
    group_of: dict[str, argparse._ArgumentGroup] = {}
    for f in dataclasses.fields(cls):
        if f.name in skip:
            continue
        path = (*prefix, f.name)
        hint = hints[f.name]
        default = getattr(defaults, f.name)
        if dataclasses.is_dataclass(hint):
            added += add_config_options(parser, hint, path)
            continue
        title = groups.get(f.name) or (f"{prefix[-1]} settings" if prefix else "")
        target = parser
        if title:
            target = group_of.setdefault(title, parser.add_argument_group(title))
        flag = "--" + "-".join([p.replace("_", "-") for p in prefix] + [_flag_name(f.name)])
        dest = "cfg__" + "__".join(path)
        kwargs: dict = {"dest": dest, "default": argparse.SUPPRESS}
        args = typing.get_args(hint)
        optional = type(None) in args
        base = next((a for a in args if a is not type(None)), hint) if optional else hint
        if base is bool:
            kwargs["action"] = argparse.BooleanOptionalAction
        elif typing.get_origin(base) is typing.Literal:
            kwargs["choices"] = list(typing.get_args(base))
        elif typing.get_origin(base) is tuple:
            element = typing.get_args(base)[0]
            kwargs.update(nargs=len(typing.get_args(base)), type=element, metavar=element.__name__.upper())
        elif base in (int, float, str):
            kwargs["type"] = _none_or(base) if optional else base
            kwargs["metavar"] = base.__name__.upper()
        else:
            continue  # a type no flag can carry
        shown = "none" if default is None else default
        help_text = docs.get(f.name, "")
        kwargs["help"] = f"{help_text} (default: {shown})" if help_text else f"(default: {shown})"
        target.add_argument(flag, **kwargs)
        added.append(FieldOption(path, flag, dest))
    return added


def set_field(config, path: tuple[str, ...], value) -> None:
    """Set the field at ``path`` of a config, ``("init", "use_sfm")`` being ``config.init.use_sfm``."""
    target = config
    for name in path[:-1]:
        target = getattr(target, name)
    setattr(target, path[-1], value)


def apply_options(config, args: argparse.Namespace, options: list[FieldOption]) -> list[str]:
    """Set the fields of ``config`` given on the command line; returns the field paths that were set."""
    given = []
    for option in options:
        if not hasattr(args, option.dest):
            continue
        value = getattr(args, option.dest)
        set_field(config, option.path, tuple(value) if isinstance(value, list) else value)
        given.append(".".join(option.path))
    return given


def option_names(options: list[FieldOption]) -> dict[str, str]:
    """``{"densify.max_gaussians": "--densify-max-gaussians", ...}`` for naming options in errors."""
    return {".".join(o.path): o.flag for o in options}

