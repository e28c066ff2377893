"""Typed dataclass configs turned into command lines and parsed from strings (CleanRL-style ``Args``).

A config is a ``@dataclass`` whose fields carry a type, a default and a docstring (the string literal under
the field, which becomes its ``--help``)::

    @dataclass
    class Args:
        steps: int = 1000
        \"\"\"Optimiser steps.\"\"\"
        mode: str = field(default="fast", metadata={"choices": ("fast", "exact")})
        \"\"\"How to solve.\"\"\"

    args = parse_config(Args, ["--steps", "10"], prog="python -m tool")

One flag per field, ``--snake-case``. Types map to argparse as:

- ``bool``: ``--flag`` / ``--no-flag`` (``BooleanOptionalAction``);
- ``int``, ``float``, ``str``; ``X | None`` also accepts ``none``;
- ``tuple[float, float]``: ``nargs=2``; ``tuple[int, ...]`` and ``list[int]``: ``nargs="+"``;
- ``Literal["a", "b"]`` or ``metadata={"choices": ...}``: argparse ``choices``.

Modules may use ``from __future__ import annotations``: types are resolved with :func:`typing.get_type_hints`.
:func:`convert` turns one string into a field's type by the same rules (used for ``name:key=value`` policy
options, see :func:`detaug_gym.policies.parse_policy_options`). This module imports only the standard library.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import numbers
import os
import re
import textwrap
import types
import typing
from collections.abc import Iterable, Mapping
from typing import Any, Literal, TypeVar, Union

T = TypeVar("T")
TRUE_WORDS, FALSE_WORDS = ("true", "1", "yes"), ("false", "0", "no")
NONE_WORDS = ("none", "null")


# ---------------------------------------------------------------------------------------------- introspection
def field_docs(cls: type) -> dict[str, str]:
    """Attribute docstrings (the string literal under each field) of a dataclass and its dataclass bases."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        try:
            source = textwrap.dedent(inspect.getsource(klass))
        except (OSError, TypeError):  # no source (built in a REPL): no help text
            continue
        body = ast.parse(source).body[0].body
        for node, nxt in zip(body, body[1:]):
            if (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and isinstance(nxt, ast.Expr)
                    and isinstance(nxt.value, ast.Constant) and isinstance(nxt.value.value, str)):
                docs[node.target.id] = inspect.cleandoc(nxt.value.value) if "\n" in nxt.value.value \
                    else nxt.value.value
    return docs


@dataclasses.dataclass(frozen=True)
class FieldType:
    """What a field's annotation means for parsing.

    Attributes:
        base: the scalar type of a value or of each item (``int``, ``float``, ``str``, ``bool``).
        optional: ``None`` is allowed.
        count: ``None`` for a scalar, an int for a fixed-length tuple, ``"+"`` for a list or ``tuple[X, ...]``.
        container: ``tuple`` or ``list`` for sequences, else ``None``.
        choices: allowed values (``Literal`` type or ``metadata={"choices": ...}``), or ``None``.
    """

    base: type
    optional: bool = False
    count: int | str | None = None
    container: type | None = None
    choices: tuple | None = None


def _is_union(hint: Any) -> bool:
    return typing.get_origin(hint) is Union or isinstance(hint, types.UnionType)


def field_type(hint: Any, choices: Iterable | None = None) -> FieldType:
    """Decompose a resolved annotation (``int | None``, ``tuple[float, float]``, ``Literal[...]``, ...)."""
    optional = False
    if _is_union(hint):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        optional = len(args) < len(typing.get_args(hint))
        if len(args) != 1:
            raise TypeError(f"unsupported union type {hint!r}: use one type or X | None")
        hint = args[0]
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    count, container = None, None
    if origin in (tuple, list):
        container = origin
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(set(args)) != 1:
                raise TypeError(f"unsupported tuple type {hint!r}: items must share one type")
            count = len(args)
        else:
            count = "+"
        hint = args[0] if args else str
        origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is Literal:
        choices = args if choices is None else choices
        hint = type(args[0])
    if hint not in (int, float, str, bool):
        raise TypeError(f"unsupported field type {hint!r}: use bool, int, float, str, Literal, tuple or list")
    return FieldType(hint, optional, count, container, None if choices is None else tuple(choices))


def config_fields(cls: type) -> dict[str, tuple[dataclasses.Field, FieldType]]:
    """Every init field of dataclass ``cls`` with its parsed type (annotations resolved, future-import safe)."""
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"{cls!r} is not a dataclass")
    hints = typing.get_type_hints(cls, include_extras=False)
    return {f.name: (f, field_type(hints[f.name], f.metadata.get("choices")))
            for f in dataclasses.fields(cls) if f.init}


def field_default(f: dataclasses.Field) -> Any:
    """A field's default value (calls ``default_factory``); ``dataclasses.MISSING`` when it has none."""
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return dataclasses.MISSING


# ---------------------------------------------------------------------------------------------- strings -> values
def parse_bool(text: str, name: str = "value") -> bool:
    """``true/false``, ``1/0``, ``yes/no`` in any case; anything else raises ``ValueError``."""
    word = str(text).strip().lower()
    if word in TRUE_WORDS:
        return True
    if word in FALSE_WORDS:
        return False
    raise ValueError(f"{name} expects a boolean (true/false, 1/0, yes/no), got {text!r}")


def _scalar(text: str, base: type, name: str) -> Any:
    text = text.strip()
    if base is bool:
        return parse_bool(text, name)
    if base is int:
        if not re.fullmatch(r"[+-]?\d+", text):
            raise ValueError(f"{name} expects an integer, got {text!r}")
        return int(text)
    if base is float:
        try:
            return float(text)
        except ValueError:
            raise ValueError(f"{name} expects a number, got {text!r}") from None
    return text


def convert(text: str, kind: FieldType, name: str = "value") -> Any:
    """One string to a value of ``kind``: ``"8"`` -> 8, ``"no"`` -> False, ``"0.1 0.2 0.3"`` -> (0.1, 0.2, 0.3).

    Sequence items are separated by commas and/or whitespace (brackets are allowed around them); an optional
    field takes ``none``/``null``. Raises ``ValueError`` naming ``name``, the expected type or the valid choices.
    """
    if kind.optional and str(text).strip().lower() in NONE_WORDS:
        return None
    if kind.count is None:
        return check_choices(_scalar(str(text), kind.base, name), kind, name)
    items = [item for item in re.split(r"[,\s]+", str(text).strip().strip("()[]")) if item]
    if isinstance(kind.count, int) and len(items) != kind.count:
        raise ValueError(f"{name} expects {kind.count} values, got {len(items)} in {text!r}")
    if not items:
        raise ValueError(f"{name} expects at least one value, got {text!r}")
    return kind.container(check_choices(_scalar(item, kind.base, name), kind, name) for item in items)


def check_choices(value: Any, kind: FieldType, name: str = "value") -> Any:
    """``value`` if ``kind`` has no choices or it is one of them, else a ``ValueError`` listing them."""
    if kind.choices is not None and value not in kind.choices:
        raise ValueError(f"unknown {name} {value!r}; valid: {', '.join(map(str, kind.choices))}")
    return value


def check_value(value: Any, kind: FieldType, name: str = "value") -> Any:
    """A typed value (from Python code, not a string) checked against ``kind``; returns it normalised
    (``numpy`` integers -> ``int``, ints -> ``float`` for float fields, lists -> tuples for tuple fields).
    Strings are accepted for str fields, and ``os.PathLike`` too (paths are kept as given)."""
    if value is None:
        if kind.optional:
            return None
        raise ValueError(f"{name} must not be None")
    if kind.count is not None:
        if isinstance(value, (str, bytes)) or not isinstance(value, Iterable):
            raise ValueError(f"{name} expects a sequence of {kind.base.__name__}, got {value!r}")
        item = dataclasses.replace(kind, count=None, container=None, optional=False)
        items = [check_value(v, item, name) for v in value]
        if isinstance(kind.count, int) and len(items) != kind.count:
            raise ValueError(f"{name} expects {kind.count} values, got {len(items)}")
        return kind.container(items)
    if kind.base is bool:
        if not (isinstance(value, bool) or type(value).__name__ == "bool_"):  # numpy.bool_ without numpy
            raise ValueError(f"{name} expects a boolean, got {value!r}")
        value = bool(value)
    elif kind.base is int:
        if isinstance(value, bool) or not isinstance(value, numbers.Integral):
            raise ValueError(f"{name} expects an integer, got {value!r}")
        value = int(value)
    elif kind.base is float:
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise ValueError(f"{name} expects a number, got {value!r}")
        value = float(value)
    elif not isinstance(value, (str, os.PathLike)):
        raise ValueError(f"{name} expects a string, got {value!r}")
    return check_choices(value, kind, name)


# ---------------------------------------------------------------------------------------------- argparse
def _flag(name: str, prefix: str) -> str:
    return "--" + (prefix + name).replace("_", "-")


def add_dataclass_arguments(parser: argparse.ArgumentParser | argparse._ArgumentGroup, cls: type,
                            prefix: str = "", choices: Mapping[str, Iterable] | None = None) -> None:
    """Add one ``--<prefix><field>`` flag per field of dataclass ``cls`` to a parser or an argument group.

    ``prefix`` (e.g. ``"cape-"``) namespaces the flags; the destinations are then ``cape_<field>``, and
    :func:`config_from_namespace` with the same prefix collects them. ``choices`` overrides or adds the
    allowed values of fields by name. Defaults are the dataclass's; a field without one becomes required.
    """
    docs, choices = field_docs(cls), dict(choices or {})
    for name, (f, kind) in config_fields(cls).items():
        if name in choices:
            kind = dataclasses.replace(kind, choices=tuple(choices[name]))
        default = field_default(f)
        kwargs: dict[str, Any] = {"help": docs.get(name), "dest": (prefix + name).replace("-", "_")}
        if default is dataclasses.MISSING:
            kwargs["required"] = True
        else:
            kwargs["default"] = default
        if kind.base is bool and kind.count is None and not kind.optional:
            parser.add_argument(_flag(name, prefix), action=argparse.BooleanOptionalAction, **kwargs)
            continue
        scalar = dataclasses.replace(kind, count=None, container=None)
        parser.add_argument(_flag(name, prefix), type=_argparse_type(scalar), nargs=kind.count,
                            choices=kind.choices if kind.base is not bool else None, **kwargs)


def _argparse_type(kind: FieldType):
    """An argparse ``type`` callable for one item (named after the type, for argparse's error message)."""
    if kind.base in (int, float, str) and not kind.optional:
        return kind.base

    def parse(text: str) -> Any:
        return convert(text, dataclasses.replace(kind, choices=None))  # argparse checks choices itself

    parse.__name__ = kind.base.__name__
    return parse


def config_from_namespace(cls: type[T], namespace: argparse.Namespace, prefix: str = "") -> T:
    """Build ``cls`` from the values :func:`add_dataclass_arguments` (same ``prefix``) put in ``namespace``."""
    values = {}
    for name, (_, kind) in config_fields(cls).items():
        value = getattr(namespace, (prefix + name).replace("-", "_"))
        if kind.container is not None and value is not None:
            value = kind.container(value)
        values[name] = value
    return cls(**values)


def build_parser(cls: type, prog: str | None = None, description: str | None = None,
                 choices: Mapping[str, Iterable] | None = None,
                 formatter_class: type[argparse.HelpFormatter] = argparse.RawDescriptionHelpFormatter,
                 ) -> argparse.ArgumentParser:
    """An ``ArgumentParser`` with one flag per field of dataclass ``cls`` (see the module doc)."""
    parser = argparse.ArgumentParser(prog=prog, description=description, formatter_class=formatter_class)
    add_dataclass_arguments(parser, cls, choices=choices)
    return parser


def parse_config(cls: type[T], argv: list[str] | None = None, prog: str | None = None,
                 description: str | None = None, choices: Mapping[str, Iterable] | None = None) -> T:
    """Parse ``argv`` (default ``sys.argv[1:]``) into an instance of dataclass ``cls``."""
    parser = build_parser(cls, prog, description, choices)
    return config_from_namespace(cls, parser.parse_args(argv))
