"""Official SafeLIBERO scenarios: files in SafeLIBERO's format that the tests write themselves (a LIBERO bddl with
obstacle objects and a base, models from LIBERO's assets, init files saved from the scene with torch.save), and,
when ``SAFELIBERO_ROOT`` points at a real checkout, the 32 real scenarios."""

import os
import pickle
import shutil
import zipfile
from pathlib import Path

import gymnasium as gym
import mujoco
import numpy as np
import pytest
import torch

import detaug_gym  # noqa: F401
from detaug_gym.envs.official import (
    SafeLiberoFiles,
    lift_out_of_penetration,
    read_init_file,
    register_obstacle_objects,
)
from detaug_gym.envs.suites import SUITES

TASK = SUITES["spatial"].tasks[0]
MODELS = {"moka_pot_obstacle": "turbosquid_objects/moka_pot",
          "red_coffee_mug_obstacle": "turbosquid_objects/red_coffee_mug",
          "box_base": "turbosquid_objects/white_storage_box"}
OBSTACLE_XY = np.array([0.12, -0.08])
MOKA_HALF_HEIGHT = 0.0666  # LIBERO's moka pot: its collision boxes reach 6.66 cm below its origin


def _table_top(model, data, exclude: int = -1) -> float:
    """Height of the first surface below OBSTACLE_XY (the table), passing through body ``exclude``."""
    geom = np.zeros(1, np.int32)
    origin = np.array([*OBSTACLE_XY, 3.0])
    return 3.0 - mujoco.mj_ray(model, data, origin, np.array([0.0, 0.0, -1.0]), None, 1, exclude, geom)


def _libero_bddl() -> str:
    from libero.libero import benchmark, get_libero_path

    task = benchmark.get_benchmark("libero_spatial")(task_order_index=0).get_task(0)
    return Path(f"{get_libero_path('bddl_files')}/{task.problem_folder}/{task.bddl_file}").read_text()


def _region(name: str, x0: float, y0: float) -> str:
    return (f"      ({name}\n          (:target main_table)\n          (:ranges (\n"
            f"              ({x0} {y0} {x0 + 0.02} {y0 + 0.02})\n            )\n          )\n      )\n")


def _write_bddl(path: Path) -> None:
    text = _libero_bddl()
    regions = _region("moka_region", 0.3, -0.3) + _region("mug_region", -0.3, 0.1) + _region("base_region", -0.5, -0.2)
    text = text.replace("    )\n\n  (:fixtures", regions + "    )\n\n  (:fixtures", 1)
    text = text.replace("    plate_1 - plate\n", "    plate_1 - plate\n    moka_pot_obstacle_1 - moka_pot_obstacle\n"
                        "    red_coffee_mug_obstacle_1 - red_coffee_mug_obstacle\n    box_base_1 - box_base\n", 1)
    text = text.replace("    (On flat_stove_1 main_table_stove_region)\n",
                        "    (On flat_stove_1 main_table_stove_region)\n"
                        "    (On moka_pot_obstacle_1 main_table_moka_region)\n"
                        "    (On red_coffee_mug_obstacle_1 main_table_mug_region)\n"
                        "    (On box_base_1 main_table_base_region)\n", 1)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    """A SafeLIBERO folder for Spatial task 0: level I drops the moka pot from 10 cm above the table, level II
    starts it 2 cm inside the table (as some official Long states do); the mug and the base are parked."""
    from libero.libero import get_libero_path

    from detaug_gym.envs.safe_libero import compile_libero

    top = tmp_path_factory.mktemp("safelibero")
    for category, source in MODELS.items():
        folder = top / "assets" / "obstacle_objects" / category
        shutil.copytree(Path(get_libero_path("assets")) / source, folder)
        xml = next(p for p in folder.glob("*.xml") if p.stem == Path(source).name)
        xml.rename(folder / f"{category}.xml")
    files = SafeLiberoFiles(top)
    _write_bddl(files.bddl("spatial", TASK))
    register_obstacle_objects(files, list(MODELS))
    sim = compile_libero(str(files.bddl("spatial", TASK)))
    m, state = sim.sim.model._model, sim.sim.get_state().flatten()

    def adr(name: str) -> int:
        return 1 + int(m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, f"{name}_joint0")])

    table_top = _table_top(m, sim.sim.data._data)
    for level, height in (("L1", MOKA_HALF_HEIGHT + 0.1), ("L2", MOKA_HALF_HEIGHT - 0.02)):
        states = []
        for i in range(50):
            s = state.copy()
            s[adr("moka_pot_obstacle_1"):][:7] = (*(OBSTACLE_XY + [0.002 * i, 0.0]), table_top + height, 1, 0, 0, 0)
            s[adr("red_coffee_mug_obstacle_1"):][:7] = (10.0, 0.0, 0.0, 1, 0, 0, 0)
            s[adr("box_base_1"):][:7] = (0.0, 20.0, 0.0, 1, 0, 0, 0)
            states.append(s)
        path = files.init_file("spatial", TASK, level)
        path.parent.mkdir(parents=True, exist_ok=True)
        torch.save(np.stack(states), path)
    sim.close()
    return top


def test_an_official_episode_is_its_state_settled_and_observed_like_ours(root):
    env = gym.make("SafeLibero-Spatial-L1-v0", scenarios="official", task=TASK.official, safelibero_root=str(root))
    assert env.spec.max_episode_steps == 220
    obs, info = env.reset(options={"episode": 7})
    assert info["obstacle"] == "moka_pot" and info["init_state"] == 7 and not info["collision"]
    assert obs["obstacle_mask"][0] == 1.0 and obs["obstacle_points"].shape == (256, 3)
    official = read_init_file(SafeLiberoFiles(root).init_file("spatial", TASK, "L1"))[7]
    scene = env.unwrapped.scene
    joint = mujoco.mj_name2id(scene.model, mujoco.mjtObj.mjOBJ_JOINT, "moka_pot_obstacle_1_joint0")
    start_z = official[3 + scene.model.jnt_qposadr[joint]]
    assert np.linalg.norm(obs["obstacle_pose"][:2] - (OBSTACLE_XY + [0.014, 0.0])) < 0.01  # landed where it was put
    assert obs["obstacle_pose"][2] < start_z - 0.05  # it fell ...
    table = _table_top(scene.model, scene.data, scene.obstacles["moka_pot"].body_id)
    assert abs(obs["obstacle_points"][:, 2].min() - table) < 0.01  # ... onto the table
    for _ in range(3):
        obs, _, _, _, info = env.step(np.zeros(7, np.float32))
    assert not info["collision"] and info["min_clearance"] > 0
    # same observation keys and shapes as the procedural scenarios: every zoo policy runs unchanged
    assert env.observation_space == gym.make("SafeLibero-Spatial-L1-v0").observation_space
    # the seed picks an episode (drawn like a procedural init state): one seed, one episode
    assert env.reset(seed=5)[1]["init_state"] == env.reset(seed=5)[1]["init_state"]
    with pytest.raises(ValueError, match=r"episode must be an index .*\[0, 50\)"):
        env.reset(options={"episode": 50})
    env.close()


def test_an_obstacle_started_inside_the_table_is_lifted_out_before_the_settle(root):
    env = gym.make("SafeLibero-Spatial-L2-v0", scenarios="official", task=0, safelibero_root=str(root))
    obs, info = env.reset(options={"episode": 0})
    for _ in range(20):
        obs, _, _, _, info = env.step(np.array([0, 0, 0, 0, 0, 0, -1], np.float32))
    assert not info["collision"], "the moka pot sank 2 cm into the table and was ejected"
    assert np.linalg.norm(obs["obstacle_pose"][:2] - OBSTACLE_XY) < 0.01
    # the lift itself: the state sinks the pot 1.95 cm into the table; lifted, nothing sinks deeper than 1 mm
    scene = env.unwrapped.scene
    scene.set_state(env.unwrapped.init_states(0)[0])
    body = scene.obstacles["moka_pot"].body_id
    assert lift_out_of_penetration(scene, [body]) == pytest.approx(0.0195, abs=2e-3)
    own = np.isin(np.arange(scene.model.ngeom), scene.collision_geoms(body))
    contacts = scene.data.contact[: scene.data.ncon]
    assert np.all(contacts.dist[own[contacts.geom1] != own[contacts.geom2]] > -1e-3)
    assert np.linalg.norm(scene.data.xpos[body][:2] - OBSTACLE_XY) < 1e-9
    env.close()


def test_missing_or_bad_safelibero_files_are_clear_errors(root, tmp_path, monkeypatch):
    monkeypatch.delenv("SAFELIBERO_ROOT", raising=False)
    with pytest.raises(FileNotFoundError, match="SAFELIBERO_ROOT"):
        gym.make("SafeLibero-Spatial-L1-v0", scenarios="official")
    with pytest.raises(FileNotFoundError, match="not a folder"):
        gym.make("SafeLibero-Spatial-L1-v0", scenarios="official", safelibero_root=str(tmp_path / "nope"))
    # the fixture folder has task 0 only: asking for the level's four tasks names the six files it lacks
    with pytest.raises(FileNotFoundError) as err:
        gym.make("SafeLibero-Spatial-L1-v0", scenarios="official", safelibero_root=str(root))
    assert "lacks 6 file(s)" in str(err.value)
    assert SUITES["spatial"].tasks[3].official + "_level_I.pruned_init" in str(err.value)
    for kwargs, match in (({"level": "Free"}, "L1 and L2 only"), ({"obstacle": "milk"}, "no effect"),
                          ({"scenarios": "real"}, "valid: procedural, official")):
        args = {"suite": "spatial", "level": "L1", "scenarios": "official", "safelibero_root": str(root), **kwargs}
        with pytest.raises(ValueError, match=match):
            from detaug_gym.envs.safe_libero import SafeLiberoEnv

            SafeLiberoEnv(**args)
    with pytest.raises(ValueError, match="scenarios='official'"):
        gym.make("SafeLibero-Spatial-L1-v0", task=0).reset(options={"episode": 0})
    # a corrupt init file, and one whose pickle would run code, are refused by name
    bad = tmp_path / "bad.pruned_init"
    bad.write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="bad.pruned_init"):
        read_init_file(bad)
    evil = tmp_path / "evil.pruned_init"
    with zipfile.ZipFile(evil, "w") as z:
        z.writestr("evil/data.pkl", pickle.dumps(os.system))
    with pytest.raises(ValueError, match="unexpected posix.system|unexpected nt.system"):
        read_init_file(evil)


REAL = os.environ.get("SAFELIBERO_ROOT")


@pytest.mark.skipif(not REAL, reason="SAFELIBERO_ROOT is not set (the real SafeLIBERO files)")
@pytest.mark.parametrize("suite", ["spatial", "object", "goal", "long"])
def test_every_real_scenario_settles_where_its_state_put_the_obstacle(suite):
    files = SafeLiberoFiles.locate()
    for level in ("L1", "L2"):
        env = gym.make(SUITES[suite].env_id(level), scenarios="official")
        for task, spec in enumerate(SUITES[suite].tasks_for(level)):
            state = read_init_file(files.init_file(suite, spec, level))[0]
            obs, info = env.reset(options={"task": task, "episode": 0})
            scene = env.unwrapped.scene
            body = scene.obstacles[info["obstacle"]].body_id
            qpos = scene.model.jnt_qposadr[scene.model.body_jntadr[body]]
            assert np.linalg.norm(obs["obstacle_pose"][:2] - state[1 + qpos:3 + qpos]) < 0.01, (suite, level, task)
            obs, _, _, _, info = env.step(np.zeros(7, np.float32))
            assert not info["collision"] and obs["obstacle_mask"][0] == 1.0, (suite, level, task)
        env.close()
    if suite == "goal":  # the fourth Goal task differs by level
        assert SUITES["goal"].tasks_for("L1")[3].official == "open_the_top_drawer_and_put_the_bowl_inside"
        assert SUITES["goal"].tasks_for("L2")[3].official == "put_the_cream_cheese_in_the_bowl"


def test_the_bench_plans_official_episodes_per_task_and_leaves_out_infeasible_cells():
    from detaug_gym import bench

    cfg = bench.BenchConfig(methods=["scripted"], suites=["spatial", "long"], levels=["1"], episodes=2,
                            scenarios="official", cells="feasible")
    jobs = bench.plan_jobs(cfg.methods, cfg.suites, ["L1"], cfg.episodes, cfg.seeds, cfg=cfg)
    assert len(jobs) == 12  # 2 episodes x tasks 1-3, in both suites (task 0 is left out at L1)
    assert {(j.suite, j.key.task, dict(j.reset_options)["episode"]) for j in jobs} == {
        (s, t, e) for s in ("spatial", "long") for t in (1, 2, 3) for e in (0, 1)}
    assert all(dict(j.env_kwargs)["scenarios"] == "official" for j in jobs)
    assert "spatial L1 task 0" in " ".join(cfg.notes()) and "long L1 task 0" in " ".join(cfg.notes())
    aegis = bench.BenchConfig(suites=["long"], step_limits="aegis")
    assert aegis.cell_env_kwargs("long") == {"max_episode_steps": 550}
    with pytest.raises(ValueError, match="50 per task"):
        bench.BenchConfig(scenarios="official", episodes=51)
    with pytest.raises(ValueError, match="--scenarios official only"):
        bench.BenchConfig(safelibero_root="/x")


def test_the_bench_refuses_incomplete_files_and_mixed_scenarios(root, tmp_path, monkeypatch):
    from detaug_gym import bench

    monkeypatch.delenv("SAFELIBERO_ROOT", raising=False)
    cfg = bench.BenchConfig(methods=["scripted"], levels=["1"], episodes=1, scenarios="official",
                            safelibero_root=str(root), out=str(tmp_path / "a"))
    with pytest.raises(SystemExit, match="cannot run:(.|\n)*pick_up_the_black_bowl_on_the_ramekin"):
        bench.run(cfg)
    with pytest.raises(SystemExit, match="newton has no official"):
        bench.run(bench.BenchConfig(suites=["newton"], levels=["2"], scenarios="official", out=str(tmp_path / "b")))
    procedural = dict(methods=["random"], suites=["newton"], levels=["2"], episodes=1, out=str(tmp_path / "c"),
                      env_kwargs=["max_episode_steps=3"])
    bench.run(bench.BenchConfig(**procedural))
    with pytest.raises(SystemExit, match="--settle differs"):
        bench.run(bench.BenchConfig(**procedural, settle="still"))


@pytest.mark.skipif(not REAL, reason="SAFELIBERO_ROOT is not set (the real SafeLIBERO files)")
def test_the_bench_runs_real_official_episodes(tmp_path):
    import json

    from detaug_gym import bench

    text = bench.run(bench.BenchConfig(methods=["scripted"], levels=["2"], episodes=1, scenarios="official",
                                       out=str(tmp_path), env_kwargs=["max_episode_steps=30"]))
    lines = [json.loads(x) for x in (tmp_path / "episodes.jsonl").read_text().splitlines()]
    assert sorted(r["task"] for r in lines) == [0, 1, 2, 3] and {r["init_state"] for r in lines} == {0}
    assert all(r["termination"] != "error" for r in lines) and "official SafeLIBERO episodes" in text
