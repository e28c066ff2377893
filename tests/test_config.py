"""Dataclass configs -> argparse (detaug_gym.config): flags, types, help and string conversion."""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field
from typing import Literal

import pytest

from detaug_gym.config import (
    add_dataclass_arguments,
    build_parser,
    config_fields,
    config_from_namespace,
    convert,
    parse_bool,
    parse_config,
)


@dataclass
class Args:
    steps: int = 100
    """Optimiser steps."""
    rate: float = 0.5
    """Learning rate."""
    name: str = "run"
    """Run name."""
    fast: bool = True
    """Use the fast path."""
    seed: int | None = None
    """Seed; none draws one."""
    box: tuple[float, float] = (0.0, 1.0)
    """Lower and upper bound."""
    keys: list[str] = field(default_factory=lambda: ["a", "b"])
    """Keys to keep."""
    mode: Literal["x", "y"] = "x"
    """Mode (Literal choices)."""
    kind: str = field(default="p", metadata={"choices": ("p", "q")})
    """Kind (metadata choices)."""


def test_defaults_and_every_field_type():
    assert parse_config(Args, []) == Args()
    cfg = parse_config(Args, ["--steps", "7", "--rate", "1e-3", "--no-fast", "--seed", "3", "--box", "-1", "2",
                              "--keys", "k", "--mode", "y", "--kind", "q", "--name", "z"])
    assert cfg == Args(steps=7, rate=1e-3, name="z", fast=False, seed=3, box=(-1.0, 2.0), keys=["k"], mode="y",
                       kind="q")
    assert isinstance(cfg.box, tuple)
    assert parse_config(Args, ["--seed", "none"]).seed is None


@pytest.mark.parametrize("argv", [["--steps", "2.5"], ["--mode", "z"], ["--kind", "r"], ["--box", "1"],
                                  ["--fast", "1"]])
def test_bad_values_are_argparse_errors(argv, capsys):
    with pytest.raises(SystemExit):
        parse_config(Args, argv)
    assert "error" in capsys.readouterr().err


def test_help_comes_from_the_field_docstrings():
    text = build_parser(Args, prog="tool", description="The tool.").format_help()
    for flag, doc in (("--steps", "Optimiser steps."), ("--fast, --no-fast", "Use the fast path."),
                      ("--kind {p,q}", "Kind (metadata choices)."), ("--mode {x,y}", "Mode")):
        assert flag in text and doc in text


def test_arguments_in_a_prefixed_group():
    parser = argparse.ArgumentParser()
    parser.add_argument("--steps", type=int, default=1)
    add_dataclass_arguments(parser.add_argument_group("inner"), Args, prefix="inner-")
    ns = parser.parse_args(["--steps", "5", "--inner-steps", "9", "--no-inner-fast"])
    assert ns.steps == 5 and config_from_namespace(Args, ns, prefix="inner-") == Args(steps=9, fast=False)


def test_convert_strings_by_type():
    kinds = {name: kind for name, (_, kind) in config_fields(Args).items()}
    assert convert("8", kinds["steps"]) == 8
    assert convert("NONE", kinds["seed"]) is None
    assert convert("(0.1, 0.2)", kinds["box"]) == (0.1, 0.2)
    assert convert("0.1 0.2", kinds["box"]) == (0.1, 0.2)
    for text, kind in (("2.5", "steps"), ("abc", "steps"), ("x", "rate"), ("1 2 3", "box"), ("z", "mode")):
        with pytest.raises(ValueError):
            convert(text, kinds[kind])
    assert [parse_bool(w) for w in ("True", "YES", "1", "false", "No", "0")] == [True] * 3 + [False] * 3
    with pytest.raises(ValueError, match="boolean"):
        parse_bool("maybe")
