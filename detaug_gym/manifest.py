"""The run manifest ``<out>/run.json``: what produced a bench folder (command, config, package version, git
revision, checkpoint hashes), so a table can be audited and a rerun with other settings is refused instead of
mixing two runs' episodes.

What may change between runs into one folder: methods, suites, levels, seeds and the episode count (episodes
are keyed by method, env, task, episode and seed, and the table shows the asked ones). What may not: the env
options (``--env-kwargs``, ``--scenarios``, ``--settle``, ``--step-limits``), the checkpoint behind a method
already in the folder and the seeding scheme
(:data:`detaug_gym.seeds.EPISODE_SCHEME`: a seed names other episodes under another scheme).
"""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
import time
from dataclasses import asdict
from pathlib import Path

from detaug_gym.seeds import EPISODE_SCHEME

MANIFEST = "run.json"
# Config fields that change what an episode is (with their value in folders written before they existed).
# --envs-per-worker and --device change a flow policy's arithmetic at float32 rounding, which a closed loop can
# grow into another rollout (docs/performance.md); --backend and --workers do not.
EPISODE_FIELDS = {"scenarios": "procedural", "settle": "steps", "step_limits": "suite", "envs_per_worker": 1,
                  "device": "cpu"}
CHECKPOINT_FILES = ("model.pt", "config.json", "normalization.json")


def method_checkpoints(name: str, options: dict, suite: str) -> list[Path]:
    """The checkpoint folders policy ``name`` with ``options`` loads for ``suite`` (none for policies without
    weights), found without loading them: the policy class's ``checkpoint_dirs``."""
    from detaug_gym.policies import policy_class

    dirs = getattr(policy_class(name), "checkpoint_dirs", None)
    return [Path(p) for p in dirs(suite, **options)] if callable(dirs) else []


def checkpoint_hash(path: Path) -> str | None:
    """sha256 over a checkpoint folder's inference files (None when it has none)."""
    digest, found = hashlib.sha256(), False
    for name in CHECKPOINT_FILES:
        f = path / name
        if f.exists():
            found = True
            digest.update(name.encode())
            digest.update(f.read_bytes())
    return digest.hexdigest() if found else None


def git_revision() -> str | None:
    root = Path(__file__).resolve().parents[1]
    try:
        out = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                             timeout=5, check=False)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return out.stdout.strip() or None if out.returncode == 0 else None


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("detaug_gym")
    except PackageNotFoundError:
        return "unknown"


def checkpoints(methods: list[str], suites: list[str]) -> dict[str, dict[str, str | None]]:
    """``{method spec: {suite: sha256 of its checkpoint(s)}}`` for the methods that load weights."""
    from detaug_gym.bench import parse_method

    table: dict[str, dict[str, str | None]] = {}
    for spec in methods:
        name, options = parse_method(spec)
        for suite in suites:
            hashes = [checkpoint_hash(p) for p in method_checkpoints(name, options, suite)]
            if hashes:
                table.setdefault(spec, {})[suite] = ",".join(h or "missing" for h in hashes)
    return table


def read_manifest(out: Path) -> dict | None:
    path = out / MANIFEST
    if not path.exists():
        return None
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise SystemExit(f"{path} is not valid JSON ({exc}); delete it to start the folder's record over") from None


def check_manifest(out: Path, cfg, methods: list[str], suites: list[str]) -> None:
    """Refuse a run into ``out`` whose env options or checkpoints differ from the run already there."""
    old = read_manifest(out)
    if old is None:
        return
    problems = []
    scheme = old.get("episode_scheme", 1)
    if scheme != EPISODE_SCHEME:
        problems.append(f"the folder's episodes were drawn under seeding scheme {scheme}, this version draws them "
                        f"under scheme {EPISODE_SCHEME} (the same seed is another episode)")
    for name, default in EPISODE_FIELDS.items():
        before, now = old.get("config", {}).get(name, default), getattr(cfg, name)
        if before != now:
            problems.append(f"--{name.replace('_', '-')} differs: the folder's episodes ran with {before}, this run "
                            f"asks for {now}")
    old_env = old.get("config", {}).get("env_kwargs", [])
    if sorted(old_env) != sorted(cfg.env_kwargs):
        problems.append(f"env options differ: the folder has --env-kwargs {' '.join(old_env) or '(none)'}, this run "
                        f"{' '.join(cfg.env_kwargs) or '(none)'}")
    new = checkpoints(methods, suites)
    for spec, by_suite in new.items():
        for suite, digest in by_suite.items():
            before = old.get("checkpoints", {}).get(spec, {}).get(suite)
            if before is not None and before != digest:
                problems.append(f"the checkpoint of {spec} on {suite} changed since the folder's episodes ran")
    if problems:
        raise SystemExit(f"{out} holds another run ({out / MANIFEST}):\n  " + "\n  ".join(problems)
                         + "\nuse another --out, or delete the folder to start over")


def write_manifest(out: Path, cfg, methods: list[str], suites: list[str]) -> None:
    """Write ``run.json``: this run's command and config, and the union of methods, seeds and checkpoints the
    folder's episodes came from."""
    old = read_manifest(out) or {}
    merged = dict(old.get("checkpoints", {}))
    for spec, by_suite in checkpoints(methods, suites).items():
        merged.setdefault(spec, {}).update(by_suite)
    data = {
        "command": [Path(sys.argv[0]).name, *sys.argv[1:]],
        "config": asdict(cfg),
        "detaug_gym_version": _version(),
        "git_revision": git_revision(),
        "episode_scheme": EPISODE_SCHEME,
        "checkpoints": merged,
        "updated": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "history": [*old.get("history", []), {"methods": methods, "suites": suites, "levels": cfg.levels,
                                              "seeds": cfg.seeds, "episodes": cfg.episodes}],
    }
    tmp = out / (MANIFEST + ".tmp")
    tmp.write_text(json.dumps(data, indent=1))
    tmp.replace(out / MANIFEST)
