"""Numbers the bench prints can be trusted: every episode counted, errors retried, torn lines repaired, a run
manifest that refuses mixing runs, degenerate input refused, simulator blow-ups caught, intervals, videos."""

import json
import os
import signal
import subprocess
import sys
import time

import gymnasium as gym
import numpy as np
import pytest

import detaug_gym  # noqa: F401
from detaug_gym import bench
from detaug_gym.envs.suites import SUITES
from detaug_gym.report import eval_info, paired_rows, repair_log, sign_test, summarise, table_rows, wilson


def _config(out, **kw):
    base = dict(methods=["random"], suites=["newton"], levels=["2"], episodes=2, seeds=[0], out=str(out),
                env_kwargs=["max_episode_steps=5"])
    return bench.BenchConfig(**(base | kw))


def _lines(out):
    return [json.loads(line) for line in (out / "episodes.jsonl").read_text().splitlines()]


def _record(success, collision=False, termination=None, run_seed=0, level="L2"):
    return {"method": "m", "suite": "spatial", "level": level, "env_id": f"SafeLibero-Spatial-{level}-v0", "task": 0,
            "episode": 0, "seed": 0, "success": success, "collision": collision, "run_seed": run_seed,
            "termination": termination or ("success" if success else "timeout"), "steps": 10}


def test_errored_episodes_are_failures_with_their_own_column():
    """5 successes and 5 errors read 50 % Total, not 100 %; the error count is in Table I."""
    records = [_record(True) for _ in range(5)] + [_record(False, termination="error") for _ in range(5)]
    header, rows = table_rows(summarise(records))
    cells = dict(zip(header, rows[0]))
    assert cells["Spatial Total"] == "50.0" and cells["Spatial Clean"] == "50.0"
    assert cells["Errors"] == "5" and cells["Episodes"] == "10"


def test_wilson_interval_and_seed_spread():
    lo, hi = wilson(5, 10)
    assert lo == pytest.approx(23.66, abs=0.01) and hi == pytest.approx(76.34, abs=0.01)
    assert wilson(0, 10)[0] == 0.0 and wilson(10, 10)[1] == pytest.approx(100.0)
    records = [_record(True, run_seed=0), _record(True, run_seed=0), _record(True, run_seed=1),
               _record(False, run_seed=1)]
    header, rows = table_rows(summarise(records))
    assert dict(zip(header, rows[0]))["Spatial Total"] == "75.0 ± 35.4"  # seeds at 100 and 50


def test_paired_rows_count_the_episodes_where_two_methods_differ_against_the_leader():
    """Method a is clean in episodes 0-8, b in 0-1 and 9 (a collision in 2-8), c in none; b's episode 10 has
    no partner in a and is left out of their pairing. a leads; against b: Clean 7 vs 1 (p = 0.070), Avoid 7 vs 0
    (p = 0.016), the exact two-sided sign test."""
    def rec(method, episode, clean, collision=False):
        return _record(clean, collision) | {"method": method, "episode": episode}
    records = [rec("a", i, i < 9) for i in range(10)]
    records += [rec("b", i, i in (0, 1, 9), collision=2 <= i <= 8) for i in range(11)]
    records += [rec("c", i, False) for i in range(10)]
    header, rows = paired_rows(records)
    by_method = {row[0]: dict(zip(header, row)) for row in rows}
    assert set(by_method) == {"b", "c"} and by_method["b"]["Against"] == "a"
    b = by_method["b"]
    assert (b["Episodes"], b["Clean: leader only"], b["Clean: method only"], b["Clean p"]) == ("10", "7", "1", "0.070")
    assert (b["Avoid: leader only"], b["Avoid: method only"], b["Avoid p"]) == ("7", "0", "0.016")
    assert by_method["c"]["Clean: leader only"] == "9" and by_method["c"]["Avoid p"] == "1.000"
    assert sign_test(0, 0) == 1.0 and sign_test(5, 5) == 1.0
    assert paired_rows([rec("a", 0, True)]) == ([], [])


def test_eval_info_follows_lerobots_schema():
    info = eval_info([_record(True), _record(False)])
    assert set(info) == {"per_episode", "per_task", "per_group", "overall"}
    assert info["overall"]["m"]["pc_success"] == 50.0 and info["overall"]["m"]["n_episodes"] == 2
    assert {"episode_ix", "sum_reward", "max_reward", "success", "seed"} <= set(info["per_episode"][0])


def test_a_torn_last_line_is_repaired_on_resume(tmp_path):
    bench.run(_config(tmp_path))
    log = tmp_path / "episodes.jsonl"
    with open(log, "a") as f:
        f.write('{"method": "random", "env_')  # a crash mid-write
    assert repair_log(log) == 1 and len(_lines(tmp_path)) == 2
    with open(log, "a") as f:
        f.write('{"method": "random", "env_')
    bench.run(_config(tmp_path, episodes=3))
    lines = _lines(tmp_path)
    assert sorted(r["episode"] for r in lines) == [0, 1, 2]  # the torn line neither survives nor eats a record


def test_degenerate_and_bad_values_are_errors_not_empty_tables(tmp_path, monkeypatch):
    for bad in (dict(episodes=0), dict(episodes=-1), dict(workers=0), dict(threads=0), dict(video=-1)):
        with pytest.raises(ValueError, match="must be >= "):
            _config(tmp_path, **bad)
    with pytest.raises(SystemExit, match="is a file"):
        (tmp_path / "file").write_text("x")
        bench.run(_config(tmp_path / "file"))
    with pytest.raises(SystemExit, match="cannot create"):
        bench.run(_config(tmp_path / "file" / "sub"))
    # every suite has checkpoints in the repository's zoo: an empty zoo root stands for a suite without them
    monkeypatch.setenv("DETAUG_ZOO", str(tmp_path / "empty_zoo" / "policies"))
    with pytest.raises(SystemExit, match="no checkpoint at .*empty_zoo/policies/detaug/object"):
        bench.run(_config(tmp_path / "x", methods=["detaug"], suites=["object"], levels=["1"]))
    monkeypatch.delenv("DETAUG_ZOO")
    with pytest.raises(SystemExit, match="cannot run:\n  Newton-PickPlace-Cylinder-v0 rejected the env options"):
        bench.run(_config(tmp_path / "y", env_kwargs=["no_such_option=1"]))
    for argv in (["--episodes", "0"], ["--workers", "0"]):
        with pytest.raises(SystemExit):
            bench.parse_config(argv)


def test_duplicates_count_once_and_a_run_with_other_env_options_is_refused(tmp_path):
    cfg = _config(tmp_path, methods=["random", "random"], levels=["2", "L2"], seeds=[0, 0])
    assert cfg.methods == ["random"] and cfg.seeds == [0]
    bench.run(cfg)
    assert len(_lines(tmp_path)) == 2
    manifest = json.loads((tmp_path / "run.json").read_text())
    assert manifest["config"]["env_kwargs"] == ["max_episode_steps=5"] and manifest["detaug_gym_version"]
    with pytest.raises(SystemExit, match="env options differ"):
        bench.run(_config(tmp_path, env_kwargs=["max_episode_steps=6"]))
    # another seed is its own set of episodes; the table shows the asked seeds only
    text = bench.run(_config(tmp_path, seeds=[1]))
    assert len(_lines(tmp_path)) == 4 and "| 2 |" in text.split("## Per level")[0]
    # a folder whose episodes were drawn under the seeding scheme before episode_rng (no "episode_scheme") is refused
    manifest = json.loads((tmp_path / "run.json").read_text())
    assert manifest["episode_scheme"] == 2
    del manifest["episode_scheme"]
    (tmp_path / "run.json").write_text(json.dumps(manifest))
    with pytest.raises(SystemExit, match="seeding scheme 1"):
        bench.run(_config(tmp_path, seeds=[1]))


def test_simulator_blow_up_ends_the_episode_as_an_error():
    from detaug_gym.envs.base import SimulationError

    env = gym.make("Newton-PickPlace-Cylinder-v0")
    env.reset(seed=0)
    base = env.unwrapped
    base.scene.data.qvel[base.scene.arm_qvel] = 1e6
    with pytest.raises(SimulationError, match="unstable"):
        env.step(np.zeros(7, np.float32))

    class Blower:
        def reset(self, seed=None):
            self.n = 0

        def act(self, obs):
            self.n += 1
            if self.n == 3:
                base.scene.data.qvel[:] = np.nan
            return np.zeros(7, np.float32)

    from detaug_gym.rollout import EpisodeKey, run_episode

    record = run_episode(env, Blower(), EpisodeKey("b", "Newton-PickPlace-Cylinder-v0", 0, 0, 1), "newton", "L2")
    assert record.termination == "error" and "unstable" in record.error and not record.collision
    env.close()


def test_a_killed_run_resumes_without_losing_or_repeating_episodes(tmp_path):
    # An episode takes ~0.4 s; with 6 episodes a loaded CI machine finished the run between two polls, so the kill
    # found nothing left to interrupt. 30 episodes leave seconds of run after the second line is written.
    n = 30
    argv = [sys.executable, "-m", "detaug_gym.bench", "--methods", "random", "--suites", "newton", "--levels", "2",
            "--episodes", str(n), "--env-kwargs", "max_episode_steps=40", "--out", str(tmp_path)]
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    log = tmp_path / "episodes.jsonl"
    deadline = time.time() + 120
    while time.time() < deadline and (not log.exists() or log.read_text().count("\n") < 2):
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    before = log.read_text().count("\n")
    assert 2 <= before < n
    subprocess.run(argv, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=300)
    episodes = [r["episode"] for r in _lines(tmp_path)]
    assert sorted(episodes) == list(range(n))


def test_a_ten_step_video_decodes_to_its_frames(tmp_path):
    import imageio.v3 as iio

    from detaug_gym.policies import make_policy
    from detaug_gym.rollout import rollout
    from detaug_gym.video import VideoRecorder

    env = gym.make("Newton-PickPlace-Cylinder-v0", render_mode="rgb_array")
    recorder = VideoRecorder(tmp_path / "ep.mp4", label="random")
    rollout(env, make_policy("random"), seed=0, hooks=[recorder], max_steps=10)
    path = recorder.save()
    env.close()
    frames = list(iio.imiter(path))
    assert len(frames) == 11 and frames[0].shape == (256, 256, 3)  # the start frame and one per step


def test_one_seed_gives_unrelated_episodes_in_different_cells():
    """With the task fixed, reset(seed=s) drew the same init-state index and obstacle type in every suite, level
    and task (the env's stream was the seed alone); the draws now mix in the cell, and a seed still fixes them."""
    from detaug_gym.seeds import episode_rng

    cells = [("spatial", "L1", 0), ("spatial", "L1", 1), ("spatial", "L2", 0), ("goal", "L1", 0)]
    firsts = {cell: [int(episode_rng(7, *cell).integers(50)) for _ in range(5)] for cell in cells}
    assert len({tuple(v) for v in firsts.values()}) == len(cells)

    draws = {}
    for suite, level, task in cells[:3]:
        env = gym.make(SUITES[suite].env_id(level), task=task)
        draws[(suite, level, task)] = [(info["init_state"], info["obstacle"])
                                       for info in (env.reset(seed=s)[1] for s in range(6))]
        assert env.reset(seed=3)[1]["init_state"] == draws[(suite, level, task)][3][0]
        env.close()
    assert len({tuple(v) for v in draws.values()}) == 3
    init_states = [[d[0] for d in v] for v in draws.values()]
    assert init_states[0] != init_states[1] != init_states[2]


def test_importing_the_bench_leaves_mujoco_unloaded_so_main_can_choose_egl():
    """bench.main sets MUJOCO_GL=egl for --video before MuJoCo loads; an import of MuJoCo at bench import time
    (through an env module) made every video episode fail with "gladLoadGL error"."""
    code = "import sys, detaug_gym.bench; sys.exit(int('mujoco' in sys.modules))"
    assert subprocess.run([sys.executable, "-c", code], env={k: v for k, v in os.environ.items()
                                                              if k != "MUJOCO_GL"}).returncode == 0
