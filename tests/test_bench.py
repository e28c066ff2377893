"""The harness: identical rollouts across methods, resumable JSONL, tables, errors recorded, SB3 adapter."""

import json

import gymnasium as gym
import numpy as np
import pytest

import detaug_gym  # noqa: F401
from detaug_gym import bench
from detaug_gym.policies import available_policies, make_policy, register_policy
from detaug_gym.sb3 import SB3Adapter


class ExplodingPolicy:
    """A policy that fails mid-episode: the bench must record the error and go on."""

    def __init__(self, **_):
        self.calls = 0

    def reset(self, seed=None):
        self.calls = 0

    def act(self, obs):
        self.calls += 1
        if self.calls > 3:
            raise RuntimeError("boom")
        return np.zeros(7, np.float32)


def _args(tmp_path, methods, episodes=2):
    return bench.BenchConfig(methods=methods, suites=["newton"], levels=["2"], episodes=episodes, seeds=[3],
                             out=str(tmp_path), env_kwargs=["max_episode_steps=12"])  # short episodes: a fast test


def _lines(tmp_path):
    return [json.loads(line) for line in (tmp_path / "episodes.jsonl").read_text().splitlines()]


def test_bench_runs_resumes_and_reports(tmp_path):
    register_policy("exploding", f"{__name__}:ExplodingPolicy")
    text = bench.run(_args(tmp_path, ["random", "exploding"]))
    lines = _lines(tmp_path)
    assert len(lines) == 4
    by_method = {m: [r for r in lines if r["method"] == m] for m in ("random", "exploding")}
    # identical rollouts: same seeds and obstacles for every method
    assert [r["seed"] for r in by_method["random"]] == [r["seed"] for r in by_method["exploding"]]
    assert [r["obstacle"] for r in by_method["random"]] == [r["obstacle"] for r in by_method["exploding"]]
    assert all(r["termination"] == "timeout" and r["steps"] == 12 for r in by_method["random"])
    assert all(r["termination"] == "error" and "boom" in r["error"] for r in by_method["exploding"])
    assert "random" in text and (tmp_path / "table.csv").exists() and (tmp_path / "results.png").exists()
    tasks = (tmp_path / "tasks.csv").read_text().splitlines()  # per-task counts; errors count as episodes
    assert tasks[0].startswith("Suite,Level,Task") and any("0/2 (0 coll., 2 err.)" in row for row in tasks[1:])
    paired = (tmp_path / "paired.csv").read_text().splitlines()  # both methods on the same 2 episodes
    assert paired[1].startswith("random,exploding,2,")  # a tie for the lead goes to the first name
    # rerunning resumes: nothing finished is repeated or lost; the errored episodes are retried
    bench.run(_args(tmp_path, ["random", "exploding"]))
    assert len(_lines(tmp_path)) == 6
    # asking for more episodes runs only the new ones
    bench.run(_args(tmp_path, ["random"], episodes=3))
    assert len(_lines(tmp_path)) == 7


def test_unknown_method_suite_level_fail_clearly(tmp_path):
    with pytest.raises(SystemExit, match="registered policies: .*random"):
        bench.run(_args(tmp_path, ["nonexistent"]))
    with pytest.raises(SystemExit, match="newton: L2, Free"):
        bench.run(bench.BenchConfig(methods=["random"], suites=["newton"], levels=["1"], out=str(tmp_path)))
    with pytest.raises(SystemExit, match="valid suites"):
        bench.parse_suites(["kitchen"])
    with pytest.raises(SystemExit, match="valid levels"):
        bench.parse_levels(["3"])


def test_method_options_parse_and_bad_options_fail_before_running(tmp_path):
    assert bench.parse_method("detaug:k=8,labels=zero,latch=True") == ("detaug", {"k": 8, "labels": "zero",
                                                                                "latch": True})
    assert bench.parse_method("Base") == ("base", {})
    with pytest.raises(SystemExit, match="name:key=value"):
        bench.parse_method("detaug:k")
    with pytest.raises(SystemExit, match="scripted:task=teleport.*unknown task recipe"):
        bench.run(_args(tmp_path, ["scripted:task=teleport"]))
    assert not (tmp_path / "episodes.jsonl").exists() or not _lines(tmp_path)


def test_episode_seeds_do_not_depend_on_method_or_order():
    jobs = bench.plan_jobs(["a", "b"], ["spatial"], ["L1", "L2"], 4, seeds=[0])
    seeds = {}
    for job in jobs:
        seeds.setdefault((job.key.env_id, job.key.episode), set()).add((job.key.seed, job.key.task))
    assert all(len(v) == 1 for v in seeds.values())
    assert {j.key.task for j in jobs} == {0, 1, 2, 3}


def test_registry_lists_names_on_unknown_policy():
    assert "random" in available_policies()
    with pytest.raises(KeyError, match="registered policies: .*random"):
        make_policy("no_such_method")


def test_sb3_evaluate_policy_runs_a_registered_policy():
    from stable_baselines3.common.evaluation import evaluate_policy

    env = gym.make("Newton-PickPlace-v0", max_episode_steps=10)
    mean, std = evaluate_policy(SB3Adapter(make_policy("random")), env, n_eval_episodes=2)
    assert mean == 0.0 and std == 0.0  # random actions never place the cube in 10 steps
    env.close()


def test_free_level_table_shows_no_avoid_and_warns_nothing():
    """Avoid is undefined without an obstacle: the table shows "-" there, and averages only defined cells."""
    import warnings

    from detaug_gym.report import summarise, table_rows

    def record(level, success, collision):
        return {"method": "m", "suite": "spatial", "level": level, "success": success, "collision": collision,
                "termination": "success" if success else "timeout"}

    free = [record("Free", True, False), record("Free", False, False)]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        header, rows = table_rows(summarise(free))
        cells = dict(zip(header, rows[0]))
        assert cells["Spatial Avoid"] == "-" and cells["Average Avoid"] == "-"
        assert cells["Spatial Total"] == "50.0" and cells["Average Timeout"] == "50.0"
        _, rows = table_rows(summarise(free + [record("L2", True, True), record("L2", True, False)]))
    cells = dict(zip(header, rows[0]))
    assert cells["Spatial Avoid"] == "50.0"  # only the L2 cell defines it
    assert cells["Spatial Total"] == "75.0"  # mean of the levels' 50 and 100


def test_paper_rows_cover_every_suite_of_table_one():
    """Our rates sit beside the paper's Table I for each of its four suites; a method or suite the paper does
    not report gets no row."""
    from detaug_gym.report import paper_rows, summarise

    def record(method, suite, level, success, collision):
        return {"method": method, "suite": suite, "level": level, "success": success, "collision": collision,
                "termination": "success" if success else "timeout"}

    records = [record("detaug", suite, level, True, False) for suite in ("spatial", "object", "goal", "long")
               for level in ("L1", "L2")] + [record("base", "object", "L1", True, False),
                                             record("cape:k=3", "long", "L2", False, True)]
    header, rows = paper_rows(summarise(records))
    by_key = {(r[0], r[1]): dict(zip(header, r)) for r in rows}
    assert set(by_key) == {("detaug", s) for s in ("spatial", "object", "goal", "long")} | {("cape:k=3", "long")}
    assert by_key[("detaug", "object")]["Clean (paper)"] == "88.5"
    assert by_key[("detaug", "goal")]["Clean (ours)"] == "100.0"
    assert by_key[("cape:k=3", "long")]["Avoid (paper)"] == "79.0"
