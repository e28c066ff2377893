"""Dataclass configs as command lines (placeholder until the shared builder lands)."""

from __future__ import annotations

import dataclasses
import typing


def add_dataclass_arguments(parser, cls: type) -> None:
    """One ``--flag`` per field of ``cls``."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        flag = "--" + f.name.replace("_", "-")
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        hint = hints[f.name]
        if typing.get_origin(hint) is list:
            (item,) = typing.get_args(hint)
            parser.add_argument(flag, nargs="*" if f.name == "env_kwargs" else "+", type=item, default=default)
        else:
            parser.add_argument(flag, type=hint, default=default)
