"""The Ray backend on a real local Ray instance (2 CPUs, started here): the same records as the local
workers for the same seeds, the same JSONL / resume / report, a dead actor counted as an error."""

import json
import os
import sys

import pytest

from detaug_gym import backends, bench

ray = pytest.importorskip("ray")

TIMING = ("wall_time",)


@pytest.fixture(scope="module")
def ray_instance():
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


def _records(out):
    lines = [json.loads(line) for line in (out / "episodes.jsonl").read_text().splitlines()]
    return {bench.record_key(r): {k: v for k, v in r.items() if k not in TIMING} for r in lines}


def _config(out, **kw):
    base = dict(methods=["scripted", "base"], suites=["spatial"], levels=["2"], episodes=2, seeds=[3], out=str(out),
                env_kwargs=["max_episode_steps=40"])
    return bench.BenchConfig(**(base | kw))


def test_ray_bench_gives_the_local_records_and_resumes(ray_instance, tmp_path):
    """A two-episode Ray bench per method: per-episode records identical to local workers, then a rerun skips
    everything and rewrites the same table."""
    local, remote = tmp_path / "local", tmp_path / "ray"
    bench.run(_config(local, workers=1))
    table = bench.run(_config(remote, backend="ray", workers=2))
    ours, theirs = _records(local), _records(remote)
    assert len(ours) == 4 and set(ours) == set(theirs)
    for key in ours:
        assert theirs[key] == ours[key], key
    assert all(r["termination"] != "error" for r in theirs.values())
    assert (remote / "table.md").read_text() == (local / "table.md").read_text()
    before = (remote / "episodes.jsonl").read_text()
    assert bench.run(_config(remote, backend="ray", workers=2)) == table
    assert (remote / "episodes.jsonl").read_text() == before  # nothing rerun


def _crash_on_one(job):
    if job == 1:
        os._exit(3)  # the worker process dies as a segfaulting simulator would
    return {"job": job, "pid": os.getpid()}


def test_a_dead_actor_is_an_error_record_and_is_replaced(ray_instance):
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the test module is not importable there
    results = list(backends.run_jobs([0, 1, 2, 3], _crash_on_one, lambda job, err: {"job": job, "error": err},
                                     backend="ray", workers=2))
    by_job = {r["job"]: r for r in results}
    assert sorted(by_job) == [0, 1, 2, 3]
    assert "worker died" in by_job[1]["error"]
    assert all("pid" in by_job[j] for j in (0, 2, 3))


def test_ray_needs_enough_cpus_and_address_needs_ray(ray_instance, capsys):
    with pytest.raises(SystemExit, match="needs 8 CPUs but the Ray cluster has 2"):
        list(backends.run_jobs([0], _crash_on_one, lambda j, e: {}, backend="ray", workers=8))
    for argv, message in ((["--address", "auto"], "--address is read by --backend ray only"),
                          (["--backend", "dask"], "invalid choice: 'dask'")):
        with pytest.raises(SystemExit):
            bench.parse_config(argv)
        assert message in capsys.readouterr().err
