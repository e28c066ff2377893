"""The augmentation run shared by every mode: input/output files, resume, progress bar and the report.

A *mode* is a :class:`~detaug_gym.augment.engine.Mode` (it proposes plans; the engine checks, replays and
records them per source demo, :func:`~detaug_gym.augment.engine.augment_source`). :data:`MODES` maps its
name to ``"module:attribute"``, so only the chosen mode is imported.

Output layout: the originals first (``label`` = zeros, ``augmented = False``), then per source its
accepted copies (``augmented = True``, ``source_demo``, ``augment_mode``, ``transits``, ``augment_params`` and
the mode's own attributes), written through :class:`detaug_gym.data.DatasetWriter`. A sidecar JSON file
(``<out>.progress.json``) lists the finished sources and the running statistics; on restart, sources
already listed are skipped and copies of an unfinished source are dropped and redone.
"""

from __future__ import annotations

import importlib
import json
import os
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from detaug_gym.data.dataset import DatasetError

MODES = {"detaug": "detaug_gym.augment.detaug:MODE", "demogen": "detaug_gym.augment.demogen:MODE"}


def load_mode(name: str):
    """The :class:`~detaug_gym.augment.engine.Mode` called ``name`` (imported now); ``ValueError`` lists the
    valid names."""
    if name not in MODES:
        raise ValueError(f"unknown mode {name!r}; valid modes: {', '.join(MODES)}")
    module, attribute = MODES[name].split(":")
    return getattr(importlib.import_module(module), attribute)


@dataclass
class RunStats:
    """Counts over a whole run (also over resumed parts); saved in the sidecar file."""

    suite: str = ""
    sources: int = 0
    requested: int = 0
    accepted: int = 0
    tries: int = 0
    seconds: float = 0.0
    reasons: Counter = field(default_factory=Counter)
    done: list[str] = field(default_factory=list)

    def add(self, name: str, copies: int, result) -> None:
        self.sources += 1
        self.requested += copies
        self.accepted += len(result.demos)
        self.tries += result.tries
        self.seconds += result.seconds
        self.reasons.update(result.reasons)
        self.done.append(name)

    def to_json(self) -> dict:
        return {"suite": self.suite, "sources": self.sources, "requested": self.requested,
                "accepted": self.accepted, "tries": self.tries, "seconds": self.seconds,
                "reasons": dict(self.reasons), "done": self.done}

    @classmethod
    def from_json(cls, data: dict) -> RunStats:
        stats = cls(**{k: v for k, v in data.items() if k != "reasons"})
        stats.reasons = Counter(data.get("reasons", {}))
        return stats

    def report(self) -> str:
        rate = 100.0 * self.accepted / self.tries if self.tries else 0.0
        per_demo = self.seconds / self.accepted if self.accepted else float("nan")
        reasons = ", ".join(f"{k} {v}" for k, v in self.reasons.most_common()) or "none"
        return ("| suite | sources | copies accepted / requested | samples tried | acceptance | s per accepted demo |\n"
                "|---|---:|---:|---:|---:|---:|\n"
                f"| {self.suite} | {self.sources} | {self.accepted} / {self.requested} | {self.tries} | "
                f"{rate:.1f}% | {per_demo:.1f} |\n\nrejections: {reasons}")


def progress_path(out: Path) -> Path:
    return out.with_name(out.name + ".progress.json")


def read_progress(out: Path, suite: str) -> RunStats:
    """The sidecar's statistics, or fresh ones when the output file does not exist yet."""
    side = progress_path(out)
    if out.exists() and side.exists():
        try:
            return RunStats.from_json(json.loads(side.read_text()))
        except (json.JSONDecodeError, TypeError) as exc:
            raise DatasetError(f"{side}: unreadable progress file ({exc}); delete it to redo every source") from exc
    return RunStats(suite=suite)


def check_files(inp: Path, out: Path) -> None:
    """``DatasetError`` when ``out`` is ``inp`` (the run would modify its own source) or an existing ``out``
    is not a readable HDF5 file (it could not be resumed)."""
    if inp.resolve() == out.resolve() or (out.exists() and os.path.samefile(inp, out)):
        raise DatasetError(f"{out}: is the input file too; augmenting would modify its source, choose another --out")
    if out.exists():
        import h5py

        try:
            with h5py.File(out, "r"):
                pass
        except OSError as exc:
            raise DatasetError(f"{out}: cannot resume, not a readable HDF5 file ({exc}); "
                               "delete it or choose another --out") from exc


def write_progress(out: Path, stats: RunStats) -> None:
    tmp = progress_path(out).with_suffix(".tmp")
    tmp.write_text(json.dumps(stats.to_json(), indent=1))
    tmp.replace(progress_path(out))


def drop_unfinished(out: Path, done: set[str]) -> int:
    """Delete augmented demos of sources not in ``done`` (an interrupted source is redone); returns how many."""
    if not out.exists():
        return 0
    import h5py

    dropped = 0
    with h5py.File(out, "a") as f:
        data = f.get("data")
        if data is None:
            return 0
        for name in list(data):
            attrs = data[name].attrs
            if bool(attrs.get("augmented", False)) and str(attrs.get("source_demo", "")) not in done:
                del data[name]
                dropped += 1
    return dropped


def existing_originals(out: Path) -> set[str]:
    """Names of the source demos already copied into ``out`` as originals."""
    if not out.exists():
        return set()
    import h5py

    with h5py.File(out, "r") as f:
        data = f.get("data", {})
        return {str(data[n].attrs.get("source_demo", "")) for n in data
                if not bool(data[n].attrs.get("augmented", True))}


def original_copy(demo, label_len: int):
    """The source demo as written to the output: label zeros, marked as an original."""
    from dataclasses import replace

    attrs = {k: v for k, v in demo.attrs.items() if k != "num_samples"}
    attrs.update({"source_demo": demo.name, "augmented": False})
    return replace(demo, attrs=attrs, label=np.zeros(label_len, dtype=np.float32))


def source_rng(seed: int, index: int) -> np.random.Generator:
    """Per-source generator: results do not depend on which sources a resumed run skips."""
    return np.random.default_rng([int(seed), int(index)])


@dataclass
class RunArgs:
    """What ``python -m detaug_gym.augment`` was asked to do (mode-specific options live in ``config``)."""

    inp: Path
    out: Path
    copies: int
    mode: str
    config: object
    seed: int = 0
    limit: int | None = None


def run(args: RunArgs, progress: bool = True) -> RunStats:
    """Augment every source demo of ``args.inp`` into ``args.out`` (resumable); returns the run's statistics."""
    import gymnasium as gym
    from tqdm import tqdm

    import detaug_gym  # noqa: F401  (registers the env ids)
    from detaug_gym.augment.engine import augment_source
    from detaug_gym.data import DatasetWriter, load
    from detaug_gym.envs.suites import suite_of_env

    mode = load_mode(args.mode)
    check_files(args.inp, args.out)
    dataset = load(args.inp)
    sources = select_sources(dataset.demos, args.limit)
    if not sources:
        raise DatasetError(f"{args.inp}: no demos to augment ({len(dataset.demos)} demos, none an original "
                           "collected without action noise)")
    env_args = dict(dataset.attrs.get("env_args") or {})
    env_id = env_args.get("env_name") or sources[0].attrs["env_id"]
    suite = suite_of_env(env_id)[0]
    label_len = mode.label_size(suite)
    stats = read_progress(args.out, suite.name)
    done = set(stats.done)
    drop_unfinished(args.out, done)
    env = gym.make(env_id, **env_args.get("env_kwargs", {}))
    try:
        with DatasetWriter(args.out, env_args) as writer:
            present = existing_originals(args.out)
            for demo in sources:
                if demo.name not in present:
                    writer.append(original_copy(demo, label_len))
            todo = [(i, d) for i, d in enumerate(sources) if d.name not in done]
            todo.sort(key=lambda item: round_robin_key(sources, item[0]))
            bar = tqdm(todo, desc=f"{args.mode} {env_id}", unit="demo", disable=not progress,
                       initial=len(sources) - len(todo), total=len(sources))
            for index, demo in bar:
                result = augment_source(env, demo, args.copies, source_rng(args.seed, index), mode, suite,
                                        args.config)
                for new in result.demos:
                    writer.append(new)
                stats.add(demo.name, args.copies, result)
                write_progress(args.out, stats)
                bar.set_postfix(accepted=stats.accepted, tried=stats.tries)
            bar.close()
    finally:
        env.close()
    return stats


def select_sources(demos: list, limit: int | None = None) -> list:
    """The original (not augmented) demos to augment, in file order; with ``limit``, the first ``limit`` in
    round-robin task order, so a time-boxed run gives every task its share. Demos collected with action
    noise are left out: their clean ``actions`` are not what moved the arm, so a replay could not copy them."""
    sources = [d for d in demos
               if not d.attrs.get("augmented", False) and getattr(d, "executed_actions", None) is None]
    if limit is None:
        return sources
    order = sorted(range(len(sources)), key=lambda i: round_robin_key(sources, i))[:limit]
    return [sources[i] for i in sorted(order)]


def round_robin_key(sources: list, index: int) -> tuple[int, int]:
    """Order sources task by task in turn (first demo of every task, then the second, ...), so that an
    interrupted or time-boxed run has augmented every task about equally."""
    task = int(sources[index].attrs.get("task", 0))
    rank = sum(int(d.attrs.get("task", 0)) == task for d in sources[:index])
    return rank, task


def elapsed(start: float) -> str:
    return f"{time.perf_counter() - start:.0f} s"
