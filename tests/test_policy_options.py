"""Policy options are typed dataclasses: strings convert by type and are checked without building the policy."""

from __future__ import annotations

import dataclasses
import inspect
import subprocess
import sys

import numpy as np
import pytest

from detaug_gym.policies import available_policies, make_policy, parse_policy_options, policy_options_class
from detaug_gym.policies.options import PolicyOptions

# The shipped policies (other tests register more, without options, while the suite runs).
SHIPPED = ("aegis", "base", "cape", "demogen", "detaug", "random", "scripted")


def test_every_shipped_policy_declares_its_options():
    assert set(SHIPPED) <= set(available_policies())
    for name in SHIPPED:
        assert issubclass(policy_options_class(name), PolicyOptions), name
        assert parse_policy_options(name, {}) == {}


@pytest.mark.parametrize("text, value", [("false", False), ("FALSE", False), ("No", False), ("0", False),
                                         ("true", True), ("Yes", True), ("1", True)])
def test_bool_strings_become_bools(text, value):
    assert parse_policy_options("detaug", {"latch": text}) == {"latch": value}


def test_values_convert_by_declared_type():
    parsed = parse_policy_options("detaug", {"k": "8", "guidance_scale": "2", "labels": "zero", "seed": "none",
                                             "action_steps": "5"})
    assert parsed == {"k": 8, "guidance_scale": 2.0, "labels": "zero", "seed": None, "action_steps": 5}
    assert type(parsed["k"]) is int and type(parsed["guidance_scale"]) is float
    assert parse_policy_options("random", {"scale": "0.5", "seed": "3"}) == {"scale": 0.5, "seed": 3}
    assert parse_policy_options("cape", {"refine_steps": "3", "track_cost": "yes"}) == {"refine_steps": 3,
                                                                                       "track_cost": True}
    assert parse_policy_options("detaug", {"k": 8, "latch": True}) == {"k": 8, "latch": True}  # typed already


@pytest.mark.parametrize("raw, message", [
    ({"k": "2.5"}, "k expects an integer, got '2.5'"),
    ({"k": "abc"}, "k expects an integer, got 'abc'"),
    ({"guidance_scale": "x"}, "guidance_scale expects a number"),
    ({"latch": "maybe"}, "latch expects a boolean"),
    ({"latch": "false-ish"}, "latch expects a boolean"),
    ({"k": "0"}, "k must be >= 1, got 0"),
    ({"guidance_t_min": "1.5"}, r"guidance_t_min must lie in \[0, 1\]"),
    ({"cost": "volume"}, "unknown cost 'volume'; valid: penetration, clearance"),
    ({"mode": "best"}, "valid: select, null_guidance, guided_select, null_select"),
    ({"flow_steps": "0"}, "flow_steps must be >= 1"),
    ({"noise_scale": "-0.5"}, "noise_scale must be >= 0, got -0.5"),
    ({"k": True}, "k expects an integer"),
])
def test_bad_detaug_values_are_rejected(raw, message):
    with pytest.raises(ValueError, match=message):
        parse_policy_options("detaug", raw)


def test_unknown_key_lists_the_valid_ones():
    with pytest.raises(ValueError, match=r"^unknown option 'scael' for random; valid: scale, seed$"):
        parse_policy_options("random", {"scael": "0.5"})
    with pytest.raises(ValueError, match=r"unknown option 'action_steps' for cape; valid: .*prefix_steps"):
        parse_policy_options("cape", {"action_steps": "4"})
    with pytest.raises(KeyError, match="registered policies"):
        parse_policy_options("no_such_policy", {})


def test_range_checks_of_other_policies():
    for name, raw in (("random", {"scale": "0"}), ("random", {"scale": "1.5"}), ("scripted", {"task": "juggle"}),
                      ("scripted", {"variation": "-1"}), ("cape", {"t_start": "1"}), ("cape", {"guide": "joints"}),
                      ("cape", {"prefix_steps": "0"}), ("aegis", {"alpha": "30"}), ("aegis", {"base": "aegis"}),
                      ("aegis", {"ee_semi_axes": "0.1 0 0.1"}), ("aegis", {"ee_semi_axes": "0.1 0.1"})):
        with pytest.raises(ValueError):
            parse_policy_options(name, raw)


def test_suite_is_accepted_by_every_policy():
    for name in SHIPPED:
        assert parse_policy_options(name, {"suite": "goal"}) == {"suite": "goal"}, name


def test_aegis_forwards_the_rest_to_its_wrapped_policy():
    parsed = parse_policy_options("aegis", {"base": "detaug", "alpha": "5", "k": "8", "latch": "no",
                                            "ee_semi_axes": "0.1 0.05 0.1"})
    assert parsed == {"base": "detaug", "alpha": 5.0, "k": 8, "latch": False, "ee_semi_axes": (0.1, 0.05, 0.1)}
    assert parse_policy_options("aegis", {"action_steps": "5"}) == {"action_steps": 5}  # default base: base
    with pytest.raises(ValueError, match="k expects an integer"):
        parse_policy_options("aegis", {"base": "detaug", "k": "2.5"})
    with pytest.raises(ValueError, match=r"unknown option 'k' for aegis; valid: alpha, .*wrapped base: action_steps"):
        parse_policy_options("aegis", {"k": "8"})  # base has no k
    with pytest.raises(KeyError, match="unknown policy"):
        parse_policy_options("aegis", {"base": "no_such_policy"})


def test_options_parse_without_importing_torch():
    code = ("import detaug_gym.policies as p, sys; "
            "assert p.parse_policy_options('detaug', {'k': '8'}) == {'k': 8}; "
            "p.parse_policy_options('aegis', {'base': 'cape', 't_start': '0.3'}); "
            "p.parse_policy_options('scripted', {'task': 'bowl_on_plate'}); "
            "assert 'torch' not in sys.modules, 'torch was imported'")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr


def test_constructor_defaults_match_the_options_dataclass():
    """The explicit constructor keywords and the dataclass agree on names and defaults (one source of truth for
    the checks; this pins the defaults that the light module mirrors, e.g. AEGIS's ellipsoid)."""
    from detaug_gym.models.policy import FlowPolicy
    from detaug_gym.policies import policy_class

    for name in SHIPPED:
        cls = policy_options_class(name)
        defaults = {f.name: f.default for f in dataclasses.fields(cls)}
        targets = [policy_class(name)]
        if name in ("base", "detaug", "demogen", "cape"):
            targets.append(FlowPolicy)  # their **options end up in FlowPolicy's keywords
        for target in targets:
            for param in inspect.signature(target.__init__).parameters.values():
                if param.name in ("self", "checkpoint") or param.kind is param.VAR_KEYWORD:
                    continue
                if name == "cape" and param.name == "action_steps":
                    continue  # CAPE sets FlowPolicy's action_steps from prefix_steps
                if name in ("random", "scripted") and param.name == "suite":
                    continue  # accepted and ignored
                assert param.name in defaults, (name, target, param.name)
                assert param.default == defaults[param.name], (name, param.name, param.default)
            assert "checkpoint" not in defaults or defaults["checkpoint"] is None


def test_constructors_validate_through_the_same_dataclass(tmp_path):
    missing = str(tmp_path / "nothing")  # the options fail before any checkpoint is read
    with pytest.raises(ValueError, match="k must be >= 1"):
        make_policy("detaug", checkpoint=missing, k=0)
    with pytest.raises(ValueError, match="latch expects a boolean"):
        make_policy("detaug", checkpoint=missing, latch="false")
    with pytest.raises(ValueError, match="flow_steps must be >= 1"):
        make_policy("base", checkpoint=missing, flow_steps=0)
    with pytest.raises(TypeError, match=r"unknown option 'kk' for DetAugOptions; valid: .*\bk\b"):
        make_policy("detaug", checkpoint=missing, kk=8)
    with pytest.raises(ValueError, match="t_start"):
        make_policy("cape", checkpoint=missing, t_start=2.0)
    with pytest.raises(ValueError, match="scale must lie in"):
        make_policy("random", scale=2.0)
    with pytest.raises(TypeError):
        make_policy("random", scael=0.5)
    assert make_policy("random", suite="spatial", seed=1).scale == 1.0


def test_noise_scale_shrinks_the_start_noise(tiny_base_checkpoint):
    """noise_scale multiplies the noise a plan starts from: 0 gives one plan per observation whatever the seed,
    1 (the default) varies with it, and a smaller scale keeps plans nearer each other."""
    ckpt, obs = tiny_base_checkpoint

    def plans(seed: int, **options):
        policy = make_policy("base", checkpoint=ckpt, seed=seed, **options)
        return policy.plan(obs, None, num_samples=16).numpy()

    assert np.array_equal(plans(0, noise_scale=0.0), plans(1, noise_scale=0.0))
    assert not np.allclose(plans(0), plans(1))
    assert np.allclose(plans(0, noise_scale=1.0), plans(0))  # the default is the training distribution
    spread = {scale: plans(0, noise_scale=scale).std(axis=0).mean() for scale in (0.3, 1.0)}
    assert spread[0.3] < spread[1.0], spread
