"""Build a suite's policy zoo from its declared recipe: ``python -m detaug_gym.zoo build --suite object``.

A recipe (``policies/recipes/<suite>.toml``) holds the options of every stage; this module holds the wiring
(which file feeds which command) and runs the stages as the project's own commands, each in a subprocess
with its output in ``<work>/logs/<stage>.log``::

    collect          python -m detaug_gym.collect   clean expert demos         -> <data>/<suite>.hdf5
    recovery         python -m detaug_gym.collect   recovery demos (noise)     -> <data>/<suite>_noisy.hdf5
    augment_detaug   python -m detaug_gym.augment   arc augmentations          -> <data>/<suite>_detaug.hdf5
    augment_demogen  python -m detaug_gym.augment   planned detours            -> <data>/<suite>_demogen.hdf5
    train_base       python -m detaug_gym.train     clean + recovery           -> <zoo>/base/<suite>/
    train_detaug     python -m detaug_gym.train     fine-tune from base        -> <zoo>/detaug/<suite>/
    train_demogen    python -m detaug_gym.train     fine-tune from base        -> <zoo>/demogen/<suite>/
    evaluate         python -m detaug_gym.bench     Free episodes, every method -> <work>/free/
    cards            (this module)                  a model card per checkpoint -> <zoo>/<method>/<suite>/README.md

Every stage leaves a stamp (``zoo_stage.json`` in an output folder, ``<file>.zoo.json`` beside a file, the cards'
``zoo_cards.json`` beside base's) with a key: the hash of its command and of its inputs' keys, plus the build ids
of its inputs (provenance). A rerun skips a stage whose stamp says done with the key the recipe gives now,
resumes one that was interrupted (every command resumes), rebuilds what was built from a rebuilt stage, and
leaves out a stage that is not built when nothing to run needs it (a fresh clone has the checkpoints, not the
demos). Output that the recipe no longer describes, or that the zoo did not make, is never overwritten
silently: the build stops before any work and names ``--rebuild STAGE`` (which deletes that stage's output and
rebuilds it and everything after it).

    python -m detaug_gym.zoo build --suite object --jobs 2            # plan, time estimate, then run
    python -m detaug_gym.zoo build --suite object --dry-run           # only the plan
    python -m detaug_gym.zoo build --suite object --stages evaluate cards
    python -m detaug_gym.zoo build --suite spatial --zoo /tmp/zoo --data /tmp/data   # a rebuild beside the zoo
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shlex
import shutil
import time
import tomllib
import uuid
from dataclasses import dataclass, field
from pathlib import Path

from detaug_gym.envs.suites import SUITES, get_suite

RECIPES = Path(__file__).resolve().parents[1] / "policies" / "recipes"
STAGES = ("collect", "recovery", "augment_detaug", "augment_demogen", "train_base", "train_detaug", "train_demogen",
          "evaluate", "cards")
NEEDS = {
    "collect": (), "recovery": (), "augment_detaug": ("collect",), "augment_demogen": ("collect",),
    "train_base": ("collect", "recovery"), "train_detaug": ("augment_detaug", "recovery", "train_base"),
    "train_demogen": ("augment_demogen", "train_base"),
    "evaluate": ("train_base", "train_detaug", "train_demogen"), "cards": ("evaluate",),
}
MODULES = {"collect": "detaug_gym.collect", "recovery": "detaug_gym.collect", "augment_detaug": "detaug_gym.augment",
           "augment_demogen": "detaug_gym.augment", "train_base": "detaug_gym.train",
           "train_detaug": "detaug_gym.train", "train_demogen": "detaug_gym.train", "evaluate": "detaug_gym.bench"}
# Options the zoo sets itself (the wiring); a recipe that sets one is refused.
WIRED = {"collect": ("env", "out", "task"), "augment": ("in", "out", "mode", "plot"),
         "train": ("method", "data", "out", "init_from"),
         "evaluate": ("suites", "levels", "out", "episodes", "seeds")}
CHECKPOINT_OF = {"train_base": "base", "train_detaug": "detaug", "train_demogen": "demogen"}
# Seconds per unit (demo, requested copy, training step, episode) on the 2-core machine with a second job beside
# it: the Spatial zoo's cards (policies/*/spatial), DemoGen's augmentation from the Object build. Collection,
# augmentation and evaluation scale with the suite's step limit.
RATES = {"collect": 0.77, "recovery": 1.06, "augment_detaug": 1.08, "augment_demogen": 1.0, "train_base": 0.166,
         "train_detaug": 0.23, "train_demogen": 0.72, "evaluate": 4.0, "cards": 0.0}
# A training step on both cores (threads = 2, the build gives it both) against one: 0.086-0.111 vs 0.146-0.176 s for
# the base network, measured alone on the 2-core machine (docs/models.md).
TWO_THREAD_SPEEDUP = 1.6
COMPILE_SPEEDUP = 1.4  # train --compile against eager, 1 or 2 threads (docs/models.md)
SPATIAL_STEPS = 220


class RecipeError(ValueError):
    """A recipe file that cannot be built: the message names the file, the stage and what is valid."""


# ---------------------------------------------------------------------------------------------- recipe
@dataclass
class Recipe:
    """A suite's declared recipe: per stage, its command-line options (``{"steps": 9000, ...}``), and ``tried``:
    what was measured to close a missed target (one line each, with where it is written up), which the model
    cards list under a missed status."""

    suite: str
    path: Path
    options: dict[str, dict]
    tried: tuple[str, ...] = ()

    @classmethod
    def load(cls, suite: str, path: str | os.PathLike | None = None) -> Recipe:
        """The recipe of ``suite`` (``policies/recipes/<suite>.toml`` unless ``path``); ``RecipeError`` on a
        missing file, an unknown stage or an option the zoo wires itself."""
        spec = get_suite(suite)
        path = Path(path) if path is not None else RECIPES / f"{spec.name}.toml"
        if not path.is_file():
            have = ", ".join(sorted(p.stem for p in RECIPES.glob("*.toml"))) or "none"
            raise RecipeError(f"no recipe {path} for suite {spec.name!r}; recipes in {RECIPES}: {have}")
        try:
            data = tomllib.loads(path.read_text())
        except tomllib.TOMLDecodeError as exc:
            raise RecipeError(f"{path}: not valid TOML ({exc})") from None
        declared = data.pop("suite", spec.name)
        if declared != spec.name:
            raise RecipeError(f"{path}: declares suite {declared!r}, built as {spec.name!r}")
        tried = data.pop("tried", [])
        if not isinstance(tried, list) or not all(isinstance(t, str) for t in tried):
            raise RecipeError(f"{path}: tried must be a list of strings (what was measured, one each)")
        for stage, opts in data.items():
            if stage not in STAGES or not isinstance(opts, dict):
                raise RecipeError(f"{path}: [{stage}] is not a stage; stages: {', '.join(STAGES)}")
            wired = set(opts) & set(WIRED.get(stage.split("_")[0] if stage != "recovery" else "collect", ()))
            if wired:
                raise RecipeError(f"{path}: [{stage}] sets {', '.join(sorted(wired))}, which the zoo wires itself")
        return cls(spec.name, path, {s: dict(data.get(s, {})) for s in STAGES}, tuple(tried))


def to_argv(options: dict) -> list[str]:
    """``{"noise_duty": 0.25, "progress": False, "methods": ["a", "b"]}`` -> ``--noise-duty 0.25 --no-progress
    --methods a b``."""
    argv: list[str] = []
    for key, value in options.items():
        flag = "--" + key.replace("_", "-")
        if value is True:
            argv.append(flag)
        elif value is False:
            argv.append("--no-" + key.replace("_", "-"))
        elif isinstance(value, list):
            argv += [flag, *map(str, value)]
        else:
            argv += [flag, str(value)]
    return argv


# ---------------------------------------------------------------------------------------------- stages
@dataclass
class Stage:
    """One stage of a build: its command, the files it writes, its stamp and its estimated time."""

    name: str
    argv: list[str]
    outputs: list[Path]
    stamp: Path
    needs: tuple[str, ...]
    estimate_s: float
    env: dict[str, str] = field(default_factory=dict)
    key: str = ""
    cores: int = 1
    """Cores the command keeps busy: a training's ``threads``, the evaluation's ``workers`` (else 1)."""

    @property
    def module(self) -> str | None:
        return MODULES.get(self.name)

    def command(self) -> str:
        """The shell command this stage runs (what the model cards quote)."""
        if self.module is None:
            return f"python -m detaug_gym.zoo build {shlex.join(self.argv)}"
        prefix = "".join(f"{k}={shlex.quote(v)} " for k, v in self.env.items())
        return f"{prefix}python -m {self.module} {shlex.join(self.argv)}"


@dataclass
class Paths:
    """Where a build reads and writes: demonstrations, the zoo's checkpoint root and the work folder."""

    data: Path
    zoo: Path
    work: Path

    @classmethod
    def default(cls, suite: str, data=None, zoo=None, work=None) -> Paths:
        from detaug_gym.models.policy import zoo_dir

        return cls(_relative(data or "data"), _relative(zoo or zoo_dir("base", suite).parent.parent),
                   _relative(work or Path("results") / "zoo" / suite))


def _relative(path) -> Path:
    """``path`` relative to the working directory when it lies under it: stage keys then do not depend on where
    the repository is checked out."""
    path = Path(path)
    try:
        return path.resolve().relative_to(Path.cwd().resolve())
    except ValueError:
        return path


def build_stages(recipe: Recipe, paths: Paths) -> dict[str, Stage]:
    """Every stage of ``recipe``'s build with its command wired to ``paths``, validated against the commands'
    own parsers (``RecipeError`` on an option a command does not take)."""
    spec = SUITES[recipe.suite]
    s, d, z = recipe.suite, paths.data, paths.zoo
    opts = recipe.options
    files = {"collect": d / f"{s}.hdf5", "recovery": d / f"{s}_noisy.hdf5", "augment_detaug": d / f"{s}_detaug.hdf5",
             "augment_demogen": d / f"{s}_demogen.hdf5"}
    ckpt = {name: z / method / s for name, method in CHECKPOINT_OF.items()}
    scale = spec.max_steps / SPATIAL_STEPS
    tasks = len(spec.tasks_for("Free"))
    argv: dict[str, list[str]] = {}
    estimate: dict[str, float] = {}
    cores: dict[str, int] = {}
    for name in ("collect", "recovery"):
        o = {"demos": 50, **opts[name]}
        argv[name] = ["--env", spec.env_id("Free"), "--task", "all", "--out", str(files[name])] + to_argv(o)
        _validate(recipe, name, argv[name])
        estimate[name] = RATES[name] * scale * tasks * int(o["demos"])
    sources = tasks * int({"demos": 50, **opts["collect"]}["demos"])
    for name, mode in (("augment_detaug", "detaug"), ("augment_demogen", "demogen")):
        o = {"copies": 8, **opts[name]}
        argv[name] = ["--mode", mode, "--in", str(files["collect"]), "--out", str(files[name])] + to_argv(o)
        _validate(recipe, name, argv[name])
        estimate[name] = RATES[name] * scale * min(sources, int(o.get("limit") or sources)) * int(o["copies"])
    data_of = {"train_base": [files["collect"], files["recovery"]],
               "train_detaug": [files["augment_detaug"], files["recovery"]],
               "train_demogen": [files["augment_demogen"]]}
    for name, method in CHECKPOINT_OF.items():
        o = {"steps": 9000, **opts[name]}
        init = [] if name == "train_base" else ["--init-from", str(ckpt["train_base"])]
        argv[name] = (["--method", method, "--data", ",".join(map(str, data_of[name])), "--out", str(ckpt[name])]
                      + init + to_argv(o))
        _validate(recipe, name, argv[name])
        cores[name] = max(1, int(o.get("threads", 1)))
        estimate[name] = (RATES[name] * int(o["steps"]) / (TWO_THREAD_SPEEDUP if cores[name] > 1 else 1.0)
                          / (COMPILE_SPEEDUP if o.get("compile") else 1.0))
    o = {"episodes_per_task": 20, "seed": 0, "methods": ["scripted", "base", "detaug:labels=zero", "demogen"],
         **opts["evaluate"]}
    per_task, seed, methods = o.pop("episodes_per_task"), o.pop("seed"), o.pop("methods")
    argv["evaluate"] = (["--methods", *methods, "--suites", s, "--levels", "free", "--episodes",
                         str(per_task * tasks), "--seeds", str(seed), "--out", str(paths.work / "free")]
                        + to_argv(o))
    _validate(recipe, "evaluate", argv["evaluate"])
    cores["evaluate"] = max(1, int(o.get("workers", 1)))
    estimate["evaluate"] = RATES["evaluate"] * scale * per_task * tasks * len(methods) / cores["evaluate"]
    if opts["cards"]:
        raise RecipeError(f"{recipe.path}: [cards] takes no options")
    stages = {}
    for name in STAGES:
        if name in files:
            outputs, stamp = [files[name]], files[name].with_name(files[name].name + ".zoo.json")
            if name.startswith("augment"):
                outputs.append(files[name].with_name(files[name].name + ".progress.json"))
        elif name in ckpt:
            outputs, stamp = [ckpt[name]], ckpt[name] / "zoo_stage.json"
        elif name == "evaluate":
            outputs, stamp = [paths.work / "free"], paths.work / "free" / "zoo_stage.json"
        else:
            outputs = [ckpt[n] / "README.md" for n in CHECKPOINT_OF]
            stamp = ckpt["train_base"] / "zoo_cards.json"  # committed with the cards it vouches for
        env = {"DETAUG_ZOO": str(z)} if name == "evaluate" else {}
        argv.setdefault(name, ["--suite", s, "--stages", name])  # the cards stage: this module, in process
        stages[name] = Stage(name, argv[name], outputs, stamp, NEEDS[name], estimate.get(name, 0.0), env,
                             cores=cores.get(name, 1))
    for stage in stages.values():
        deps = "".join(stages[n].key for n in stage.needs)
        stage.key = hashlib.sha256(f"{stage.command()}|{deps}".encode()).hexdigest()[:16]
    return stages


def _validate(recipe: Recipe, name: str, argv: list[str]) -> None:
    """Parse stage ``name``'s ``argv`` with its command's own parser (and config checks) without running it."""
    module = MODULES[name]
    if module == "detaug_gym.collect":
        from detaug_gym.collect import CollectArgs as cls
        parser_of = None
    elif module == "detaug_gym.train":
        from detaug_gym.models.checkpoint import METHODS
        from detaug_gym.train import TrainConfig as cls
        parser_of = {"method": METHODS}
    elif module == "detaug_gym.bench":
        from detaug_gym.bench import BenchConfig as cls
        parser_of = None
    else:
        cls = None
    try:
        if cls is not None:
            from detaug_gym.config import build_parser, config_from_namespace

            parser = build_parser(cls, prog=module, choices=parser_of)
            parser.exit_on_error = False
            ns, extra = parser.parse_known_args(argv)
            if extra:
                raise ValueError(f"unknown options {' '.join(extra)}")
            config_from_namespace(cls, ns)
        else:
            from detaug_gym.augment.__main__ import build_parser as augment_parser

            parser = augment_parser(argv[1])
            parser.exit_on_error = False
            _, extra = parser.parse_known_args(argv)
            if extra:
                raise ValueError(f"unknown options {' '.join(extra)}")
    except (ValueError, argparse.ArgumentError) as exc:
        raise RecipeError(f"{recipe.path}: [{name}]: {exc}; see python -m {module} --help") from None


# ---------------------------------------------------------------------------------------------- stamps and plan
def read_stamp(stage: Stage) -> dict | None:
    if not stage.stamp.is_file():
        return None
    try:
        return json.loads(stage.stamp.read_text())
    except json.JSONDecodeError:
        return {"key": "unreadable"}


def write_stamp(stage: Stage, state: str, stages: dict[str, Stage], **extra) -> dict:
    stamp = {"stage": stage.name, "key": stage.key, "state": state, "command": stage.command(),
             "inputs": {n: (read_stamp(stages[n]) or {}).get("build") for n in stage.needs}, **extra}
    stage.stamp.parent.mkdir(parents=True, exist_ok=True)
    tmp = stage.stamp.with_name(stage.stamp.name + ".tmp")
    tmp.write_text(json.dumps(stamp, indent=1) + "\n")
    tmp.replace(stage.stamp)
    return stamp


@dataclass
class Step:
    """What a build does with one stage: ``done`` (skip), ``resume``, ``run`` or ``rebuild`` (delete, then run)."""

    stage: Stage
    action: str
    why: str = ""


RUNS = ("run", "rebuild", "resume")


def plan(stages: dict[str, Stage], selected: list[str] | None, rebuild: list[str]) -> list[Step]:
    """The build's steps in stage order; ``RecipeError`` (before any work) on output the recipe no longer
    describes, on output the zoo did not make, or on a stage to run whose need is neither built nor selected.

    A stage is rebuilt when asked (``rebuild``) or when an input is rebuilt or resumed (its content may change);
    an input that is only made again because it is absent (the demos on a fresh clone) does not invalidate what
    was built from it. With ``selected=None`` (every stage) a stage that is not built is run only when a stage
    to run needs it: on a fresh clone with committed checkpoints and cards every stage is done or not needed
    (``--stages evaluate`` repeats the Free evaluation without collecting any data).
    """
    changes: set[str] = set()  # stages whose output will differ from what their dependents were built from
    steps, problems = [], []
    for name in STAGES:
        stage = stages[name]
        stamp = read_stamp(stage)
        present = [p for p in stage.outputs if p.exists()]
        if name in rebuild or (any(n in changes for n in stage.needs) and (present or stamp)):
            step = Step(stage, "rebuild" if present or stamp else "run",
                        "asked for" if name in rebuild else "an input is rebuilt")
        elif stamp is None:
            if present:
                problems.append(f"{name}: {present[0]} exists but was not made by the zoo (no {stage.stamp.name}); "
                                f"move it away or pass --rebuild {name}")
            step = Step(stage, "run", "not built")
        elif stamp.get("key") != stage.key:
            problems.append(f"{name}: {stage.stamp} was made by another recipe ({stamp.get('command', '?')}); the "
                            f"recipe now says: {stage.command()}. Pass --rebuild {name} to rebuild it (and what "
                            "follows), or point --zoo/--data/--work elsewhere")
            step = Step(stage, "run", "recipe changed")
        elif stamp.get("state") != "done":
            step = Step(stage, "resume", "interrupted")
        elif len(present) < len(stage.outputs):
            step = Step(stage, "rebuild", "output missing")
        else:
            step = Step(stage, "done", f"built {stamp.get('finished', '')}".strip())
        if step.action == "resume" or (step.action in RUNS and (step.why not in ("not built", "output missing")
                                                                 or any(n in changes for n in stage.needs))):
            changes.add(name)  # made from changed inputs: what was built from its old output is stale too
        steps.append(step)
    by_name = {s.stage.name: s for s in steps}
    wanted = set(STAGES if selected is None else selected)
    for step in reversed(steps):  # dependents first: whether anything to run needs a stage that is not built
        name = step.stage.name
        dependents = [by_name[n] for n in STAGES if name in stages[n].needs]
        if step.action == "done":
            continue
        if name not in wanted:
            step.action, step.why = "skip", f"not in --stages ({step.why})"
        elif (selected is None and step.why == "not built" and dependents
              and not any(d.action in RUNS for d in dependents)):
            step.action, step.why = "skip", "not needed: what is built from it is built"
    for step in steps:
        if step.action in RUNS:
            missing = [n for n in step.stage.needs if by_name[n].action == "skip"]
            if missing:
                problems.append(f"{step.stage.name} needs {', '.join(missing)}, which is not built: add it to --stages")
            stale = [n for n in STAGES if step.stage.name in stages[n].needs and step.stage.name in changes
                     and by_name[n].action == "skip" and read_stamp(stages[n]) is not None]
            if stale:
                problems.append(f"{step.stage.name} would change what {', '.join(stale)} was built from: add "
                                f"{'it' if len(stale) == 1 else 'them'} to --stages")
    if problems:
        raise RecipeError("cannot build:\n  " + "\n  ".join(problems))
    return steps


def priorities(stages: dict[str, Stage]) -> dict[str, float]:
    """Each stage's estimated time to the end of the build along its longest chain of dependents: the order in
    which ready stages start (the longest chain first)."""
    memo: dict[str, float] = {}
    for name in reversed(STAGES):
        after = [memo[n] for n in STAGES if name in stages[n].needs]
        memo[name] = stages[name].estimate_s + max(after, default=0.0)
    return memo


def wall_estimate(steps: list[Step], jobs: int) -> float:
    """Wall time of the steps to run on ``jobs`` cores, started as :func:`run_steps` does."""
    from detaug_gym.pipeline import Task, ready_tasks

    order = priorities({s.stage.name: s.stage for s in steps})
    todo = [Task(s.stage.name, s.stage.module, [], s.stage.needs, order[s.stage.name], cores=s.stage.cores,
                 estimate_s=s.stage.estimate_s)
            for s in steps if s.action in ("run", "rebuild", "resume")]
    ready = {s.stage.name for s in steps if s.action != "skip"} - {t.name for t in todo}
    running: dict[str, tuple[float, Task]] = {}  # name -> (estimated end, task)
    clock = 0.0
    while todo or running:
        for task in ready_tasks(todo, ready, [(t, end - clock) for end, t in running.values()], jobs):
            todo.remove(task)
            running[task.name] = (clock + task.estimate_s, task)
        if not running:
            break
        name = min(running, key=lambda n: running[n][0])
        clock = running.pop(name)[0]
        ready.add(name)
    return clock


def format_plan(steps: list[Step], jobs: int) -> str:
    lines = [f"{'stage':<16} {'action':<8} {'estimate':>9}  command"]
    for s in steps:
        est = f"{s.stage.estimate_s / 60:.0f} min" if s.action in ("run", "rebuild", "resume") else "-"
        lines.append(f"{s.stage.name:<16} {s.action:<8} {est:>9}  {s.stage.command()}")
        if s.why:
            lines.append(f"{'':<16} {'':<8} {'':>9}  ({s.why})")
    total = wall_estimate(steps, jobs)
    lines.append(f"estimated wall time: {total / 60:.0f} min with --jobs {jobs} (rates measured on Spatial, 2 CPU "
                 "cores; see detaug_gym/zoo.py RATES)")
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------- running
def _clear(stage: Stage) -> None:
    for path in [*stage.outputs, stage.stamp]:
        if path.is_dir():
            shutil.rmtree(path)
        elif path.exists():
            path.unlink()


def run_steps(steps: list[Step], stages: dict[str, Stage], recipe: Recipe, paths: Paths, jobs: int) -> None:
    """Run the steps with :func:`detaug_gym.pipeline.run_tasks` on ``jobs`` cores (a stage takes its
    ``cores``), the longest chain first; each stage's stamp says ``running`` while it runs and ``done`` once it
    has finished."""
    from detaug_gym.pipeline import Task, run_tasks

    order = priorities(stages)
    tasks = [Task(s.stage.name, s.stage.module, s.stage.argv, s.stage.needs, order[s.stage.name], s.stage.env,
                  call=(lambda: write_cards(stages, recipe, paths)) if s.stage.module is None else None,
                  cores=s.stage.cores, estimate_s=s.stage.estimate_s)
             for s in steps if s.action in ("run", "rebuild", "resume")]
    actions = {s.stage.name: s.action for s in steps}

    def start(task) -> None:
        if actions[task.name] == "rebuild":
            _clear(stages[task.name])
        write_stamp(stages[task.name], "running", stages, started=time.strftime("%Y-%m-%d %H:%M:%S"))

    def finish(task, seconds: float) -> None:
        write_stamp(stages[task.name], "done", stages, build=uuid.uuid4().hex[:12], seconds=round(seconds, 1),
                    finished=time.strftime("%Y-%m-%d %H:%M:%S"))

    run_tasks(tasks, jobs, paths.work / "logs", f"zoo {recipe.suite}",
              done={n for n, a in actions.items() if a == "done"}, on_start=start, on_finish=finish)


# ---------------------------------------------------------------------------------------------- cards
def write_cards(stages: dict[str, Stage], recipe: Recipe, paths: Paths) -> list[Path]:
    """A model card (``README.md``) in every checkpoint folder of the build; returns their paths."""
    from detaug_gym.model_card import card

    written = []
    for name, method in CHECKPOINT_OF.items():
        path = stages[name].outputs[0] / "README.md"
        path.write_text(card(method, name, stages, recipe, paths))
        written.append(path)
    return written


# ---------------------------------------------------------------------------------------------- CLI
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m detaug_gym.zoo", description=__doc__.split("\n")[0],
                                     epilog=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    b = sub.add_parser("build", help="build a suite's zoo from its recipe (resumable)")
    b.add_argument("--suite", required=True, help=f"suite to build: {', '.join(SUITES)}")
    b.add_argument("--recipe", default=None, help="recipe file (default policies/recipes/<suite>.toml)")
    b.add_argument("--stages", nargs="+", default=None, metavar="STAGE",
                   help=f"stages to run (default: every stage that is not built and is needed): {' '.join(STAGES)}")
    b.add_argument("--rebuild", nargs="+", default=[], metavar="STAGE",
                   help="delete these stages' output and rebuild them and every stage after them")
    b.add_argument("--jobs", type=int, default=1,
                   help="cores the build keeps busy: stages run side by side while their cores fit (a stage takes "
                        "its training's threads or its evaluation's workers, else one; default 1)")
    b.add_argument("--data", default=None, help="demonstrations folder (default data/)")
    b.add_argument("--zoo", default=None, help="checkpoint root (default the repository's policies/ or $DETAUG_ZOO)")
    b.add_argument("--work", default=None, help="logs and evaluation results (default results/zoo/<suite>)")
    b.add_argument("--dry-run", action="store_true", help="print the plan and stop")
    return parser


def main(argv: list[str] | None = None) -> None:
    parser = build_parser()
    ns = parser.parse_args(argv)
    for name in [*(ns.stages or ()), *ns.rebuild]:
        if name not in STAGES:
            parser.error(f"unknown stage {name!r}; stages: {', '.join(STAGES)}")
    if ns.jobs < 1:
        parser.error(f"--jobs must be >= 1, got {ns.jobs}")
    try:
        recipe = Recipe.load(ns.suite, ns.recipe)
        paths = Paths.default(recipe.suite, ns.data, ns.zoo, ns.work)
        stages = build_stages(recipe, paths)
        steps = plan(stages, ns.stages, ns.rebuild)
    except (RecipeError, ValueError) as exc:
        raise SystemExit(f"error: {exc}") from None
    print(f"zoo build {recipe.suite} from {recipe.path}\n{format_plan(steps, ns.jobs)}", flush=True)
    if ns.dry_run:
        return
    run_steps(steps, stages, recipe, paths, ns.jobs)
    print(f"zoo {recipe.suite}: every stage done")


if __name__ == "__main__":
    main()
