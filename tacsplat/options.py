"""Command options as typed dataclasses, parsed by tyro (help from the fields' docstrings, as gsplat's and
nerfstudio's trainers do): ``--help`` prints and exits 0, and a bad or missing value is one :class:`UsageError`
naming the option (exit 2), never tyro's box. A docstring's lines show as flowing text: :func:`flowing`."""

from __future__ import annotations

import contextlib
import io
import re
from typing import TypeVar

from tacsplat.errors import ConfigError, UsageError

T = TypeVar("T")

_RULE = re.compile(r"^[\s\u2500-\u257f|+-]*$")  # a line of box drawing (rich's, or its ASCII form)


def flowing(text: str) -> str:
    """``text`` with the lines of each paragraph joined (paragraphs: between blank lines). tyro's own joining keeps
    the break before an indented or a non-letter line, so a field docstring's second line, or one that starts
    "(use", began a new line in the middle of a sentence in --help."""
    return "\n\n".join(" ".join(paragraph.split()) for paragraph in re.split(r"\n\s*\n", text.strip()))


def _tyro():
    """tyro, joining docstrings' lines with :func:`flowing` (every help text and description goes through the
    function replaced)."""
    import tyro
    import tyro._strings

    tyro._strings.remove_single_line_breaks = flowing
    return tyro


def parse_options(cls: type[T], argv: list[str], prog: str, default: T | None = None, compact: bool = False) -> T:
    """The ``cls`` instance of ``argv`` (over ``default``'s values when given); ``compact``: --help lists the
    options without their descriptions, which -H adds. A positional's metavar is its field's name (``RUN``)."""
    tyro = _tyro()
    names = tyro.conf.PositionalMetavarFromFieldName
    shown, errors = io.StringIO(), io.StringIO()
    try:
        with contextlib.redirect_stdout(shown), contextlib.redirect_stderr(errors):
            return tyro.cli(cls, args=argv, default=default, prog=prog, compact_help=compact, config=(names,))
    except SystemExit as stop:
        if stop.code == 0:  # --help
            print(shown.getvalue(), end="")
            raise
        if unknown := _unknown_option(cls, argv, prog):  # (tyro may blame what it consumed as its value)
            raise unknown from None
        raise UsageError(*tyro_error(errors.getvalue() + shown.getvalue(), prog)) from None


def _unknown_option(cls: type, argv: list[str], prog: str) -> UsageError | None:
    """The first ``--option`` of ``argv`` that ``cls`` does not have, as a UsageError suggesting the nearest one.
    Before tyro's own message: an unknown option before a positional takes that positional as its value, and tyro
    then says the positional is missing."""
    import difflib

    known = set(options_parser(cls)._option_string_actions)  # (what tyro's parser takes: -h, --help, ...)
    for token in argv:
        if token == "--":
            break
        option = token.split("=", 1)[0]
        if option.startswith("--") and option not in known:
            near = difflib.get_close_matches(option, sorted(known), n=1)
            return UsageError(option, f"not an option of {prog}" + (f" (did you mean {near[0]}?)" if near else ""))
    return None


def options_parser(options: type):
    """The argparse parser of the dataclass ``options`` as tyro builds it (:func:`parse_options`' positional
    metavars), -h and --help included: the options it takes, and what shtab lists for the command."""
    import warnings

    tyro = _tyro()
    with warnings.catch_warnings():  # (get_parser is deprecated in tyro 1.0, yet its only argparse view of a CLI)
        warnings.simplefilter("ignore", DeprecationWarning)
        return tyro.extras.get_parser(options, config=(tyro.conf.PositionalMetavarFromFieldName,))


def tyro_error(text: str, prog: str) -> tuple[str, str]:
    """``(option, what is wrong)`` of tyro's error box: its title, a rule, then the message up to the next rule (a
    missing option or positional is named on the line after "Missing from PROG:", its help on the next)."""
    sections, current = [], []
    for line in text.splitlines():
        if _RULE.match(line):
            if current:
                sections.append(current)
            current = []
        else:
            current.append(line.strip(" \u2502|"))
    sections.append(current)
    title = " ".join(sections[0]).strip() if sections else ""
    body = sections[1] if len(sections) > 1 else []
    message = " ".join(" ".join(body).split()) or "invalid options"
    if title == "Required options":
        lines = [line for line in body if line and not line.startswith("Missing from")]
        missing = lines[0].split()[0] if lines else "options"
        if missing.startswith("--"):
            return missing, "required"
        about = lines[1].removesuffix("(required)").strip() if len(lines) > 1 else ""
        return missing, f"required ({about})" if about else "required"
    option = re.search(r"--[\w.-]+", message)
    key = option.group(0) if option else "options"
    if title == "Unrecognized options":
        return key, f"not an option of {prog}"
    message = re.sub(rf"^Error parsing {re.escape(key)}: ", "", message)
    optional = re.fullmatch(r"no type matching \{None\}\|(\S+) could be instantiated from \[(.*)\]\.?", message)
    return key, f"expected {optional[1]} (or None), got {optional[2]}" if optional else message


def comma_separated_ints(text: str, option: str) -> tuple[int, ...]:
    """The integers of an option like ``--seeds 0,1,2``; a UsageError (exit 2) naming ``option`` otherwise."""
    try:
        return tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise UsageError(option, f"expected comma-separated integers, got {text!r}") from None


def first_repeat(values):
    """The first of ``values`` (a sequence) that is there twice (None when each is there once)."""
    return next((value for i, value in enumerate(values) if value in values[:i]), None)


def options_error(exc: ConfigError, options: dict[str, str] | None = None) -> UsageError:
    """A bench config's error (one option's value at fault) as the UsageError (exit 2) naming the command-line
    option of its key: ``options[key]``, else ``--key`` (``full_views`` -> ``--full-views``)."""
    if isinstance(exc, UsageError):  # (names its option already)
        return exc
    option = (options or {}).get(exc.key, "--" + exc.key.replace("_", "-"))
    return UsageError(option, str(exc).removeprefix(f"{exc.key}: "))
