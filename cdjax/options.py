"""Command-line options built from dataclass fields: one option per field, its help the comment after the
field, its default the field's default (never copied into a help text).

    add_options(group, Config, dest="config.", skip=("arm", "num_updates"))
    add_options(group, HParams, dest="hp.", grid=True)          # --alpha 0 1.0: several values each
    given(args, "config.")                                      # {field: value} of the options given

Every option's argparse default is None, so `given` tells what was on the command line (for the
precedence defaults < preset < flags, and for what a resume may not change). The comments are read with
Python's tokenizer from the class's source: the one-line comment every field has where it is defined.
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import io
import re
import textwrap
import tokenize
import typing
from typing import Any, Literal, Mapping


def field_docs(cls) -> dict[str, str]:
    """{field: the comment on the line that defines it} of a dataclass, with the comment-only lines right below
    that line (no blank line between) as its continuation."""
    source = textwrap.dedent(inspect.getsource(cls))
    docs: dict[str, str] = {}
    depth, start, name, last, commented = 0, True, None, None, False
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.INDENT:
            depth += 1
        elif tok.type == tokenize.DEDENT:
            depth -= 1
        elif tok.type == tokenize.NEWLINE:  # the end of a statement: its comment may go on below it
            start, name, last = True, None, name if name in docs else None
        elif tok.type == tokenize.NL:  # the end of a comment-only or blank line; a blank one ends any continuation
            last = last if commented else None
            commented = False
        elif tok.type == tokenize.COMMENT:
            commented = True
            text = tok.string.lstrip("#").strip()
            if name is not None and name not in docs:
                docs[name] = text
            elif name is None and last is not None:
                docs[last] = f"{docs[last]} {text}"
        else:
            if start and depth == 1 and tok.type == tokenize.NAME:
                name = tok.string
            start, last = False, None
    return {f.name: docs.get(f.name, "") for f in dataclasses.fields(cls)}


def count(text: str) -> int:
    """An integer count: 50_000_000, 5e7 or 50000000."""
    try:
        return int(text)
    except ValueError:
        pass
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if not value.is_integer():
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number")
    return int(value)


def positive(text: str) -> int:
    """A count of at least 1 (`count`'s forms)."""
    value = count(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number of at least 1")
    return value


def non_negative(text: str) -> int:
    """A count of at least 0 (`count`'s forms): a base seed, an index."""
    value = count(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number of at least 0")
    return value


def number(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None


def seconds(text: str) -> float:
    """A positive duration in seconds: 3600, 3.6e3."""
    value = number(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"{text!r} is not a positive number of seconds")
    return value


def boolean(text: str) -> bool:
    if text.lower() in ("true", "1", "yes"):
        return True
    if text.lower() in ("false", "0", "no"):
        return False
    raise argparse.ArgumentTypeError(f"{text!r} is not true or false")


PARSERS = {int: count, float: number, str: str, bool: boolean}


def _default(field: dataclasses.Field):
    if field.default is not dataclasses.MISSING:
        return field.default
    if field.default_factory is not dataclasses.MISSING:
        return field.default_factory()
    return None


def _shown(value) -> str:
    return " ".join(map(str, value)) if isinstance(value, tuple) else str(value)


def add_options(group, cls, *, dest: str, prefix: str = "--", skip=(), grid: bool = False, switches: bool = False,
                flags: Mapping[str, str] | None = None, shown: Mapping[str, Any] | None = None) -> None:
    """One option per field of dataclass `cls` (except `skip`), stored as `<dest><field>` (None: not given).

    grid: every option takes one or more values (a hyper-parameter grid). switches: a bool field is a
    flag that flips its default (--no-<field> when it defaults to True), else it takes true/false.
    `flags` renames options ({field: "--steps"}); `shown` gives the default a help text shows where the
    field's own default stands for another value (an empty tuple for "the setting's arms").
    """
    hints = typing.get_type_hints(cls)
    docs = field_docs(cls)
    for field in dataclasses.fields(cls):
        if field.name in skip:
            continue
        hint, default = hints[field.name], _default(field)
        name = (flags or {}).get(field.name, prefix + field.name.replace("_", "-"))
        kwargs: dict[str, Any] = dict(default=None, dest=f"{dest}{field.name}")
        doc = docs[field.name]
        if switches and hint is bool:
            name = name.replace("--", "--no-", 1) if default else name
            kwargs.update(action="store_const", const=not default)
            doc = f"{doc}: this option turns it {'off' if default else 'on'}"
        elif typing.get_origin(hint) is Literal:
            kwargs.update(choices=typing.get_args(hint), metavar="{" + ",".join(typing.get_args(hint)) + "}")
        elif typing.get_origin(hint) is tuple:
            item = typing.get_args(hint)[0]
            kwargs.update(type=PARSERS[item], nargs="+", metavar=item.__name__.upper())
        elif hint in PARSERS:
            kwargs.update(type=PARSERS[hint], metavar="{true,false}" if hint is bool else hint.__name__.upper())
        else:  # pragma: no cover - a new kind of field needs a line here
            raise TypeError(f"{cls.__name__}.{field.name}: no command-line form for {hint}")
        if grid:
            kwargs.update(nargs="+", metavar="X")
        default = (shown or {}).get(field.name, default)
        help_text = (doc if switches and hint is bool else f"{doc} (default {_shown(default)})").replace("%", "%%")
        group.add_argument(name, help=help_text, **kwargs)


def given(args: argparse.Namespace, dest: str) -> dict[str, Any]:
    """{field: value} of the options stored under `dest` that the command line gave (lists as tuples)."""
    out = {}
    for key, value in vars(args).items():
        if key.startswith(dest) and value is not None:
            out[key[len(dest):]] = tuple(value) if isinstance(value, list) else value
    return out


class UsageError(ValueError):
    """Command-line input that cannot run; one sentence."""


class Parser(argparse.ArgumentParser):
    """argparse that reports errors in one line (no usage block) and exits with status 2."""

    def error(self, message: str):
        message = re.sub(r"^unrecognized arguments: ", "unknown option(s): ", message)
        raise UsageError(f"{message.replace(chr(10), ' ')}; see `{self.prog} --help`.")
