"""The paper's fine-tuning experiment ("Adapting a Pre-Trained Policy"): ``python -m detaug_gym.finetune``.

From a suite's zoo ``base`` (default Newton, the paper's pick-and-place with a cylinder), fine-tune DetAug (the
arc label) and DemoGen (the point-cloud encoder), each two ways: adapter-only (the label or cloud encoder and
the AdaLN modulation layers; the rest frozen) and full. The four runs are the zoo recipe's ``train_detaug`` and
``train_demogen`` commands on the zoo build's data, with ``--steps``, ``--snapshot-every`` (the EMA weights
every ``steps / points`` steps) and ``--adapter-only``. Every snapshot, and base itself at step 0, is evaluated
on the obstacle level with one bench run, so every point of every curve sees the same episodes. The command
writes the success and collision curves (``--figure``, default ``docs/finetune.png``) and the table
(``<out>/finetune.md``); a rerun resumes (trainings and bench both do).

    python -m detaug_gym.zoo build --suite newton --stages collect recovery augment_detaug augment_demogen train_base
    python -m detaug_gym.finetune --jobs 2                     # 2400 steps, 6 points per curve, 40 episodes each
    python -m detaug_gym.finetune --steps 1200 --points 6 --episodes 40
"""

from __future__ import annotations

import json
import textwrap
from dataclasses import dataclass
from pathlib import Path

from detaug_gym.config import parse_config
from detaug_gym.train import snapshot_dir
from detaug_gym.zoo import Paths, Recipe, build_stages

RUNS = (("detaug", "adapter"), ("detaug", "full"), ("demogen", "adapter"), ("demogen", "full"))
LABELS = {"detaug": "DetAug (label)", "demogen": "DemoGen (point cloud)"}
PAPER = "paper (adapter-only, final): DetAug 35 % success, DemoGen 2 %, base 6 %; full: DemoGen matches or beats DetAug"


@dataclass
class FinetuneConfig:
    """What ``python -m detaug_gym.finetune`` runs (every field is a flag)."""

    suite: str = "newton"
    """Suite whose zoo base and build data are fine-tuned (the paper: newton)."""
    steps: int = 2400
    """Fine-tuning steps of every run."""
    points: int = 6
    """Snapshots per curve (every steps / points steps), each evaluated."""
    episodes: int = 40
    """Bench episodes per point (the same episodes for every point)."""
    level: str = "2"
    """Obstacle level evaluated (newton: 2, the cylinder on the path)."""
    seed: int = 0
    """Bench run seed."""
    jobs: int = 2
    """Trainings at once, and bench workers."""
    data: str = "data"
    """The zoo build's demonstrations folder."""
    zoo: str | None = None
    """Checkpoint root holding base/<suite> (default the repository's policies/ or $DETAUG_ZOO)."""
    recipe: str | None = None
    """Zoo recipe giving the fine-tune options (default policies/recipes/<suite>.toml)."""
    out: str = "results/finetune"
    """Runs, logs, bench episodes and the table."""
    figure: str = "docs/finetune.png"
    """Where the curves go."""

    def __post_init__(self) -> None:
        if self.steps < 1 or self.points < 1 or self.steps % self.points:
            raise ValueError(f"--steps must be a positive multiple of --points, got {self.steps} and {self.points}")
        if self.episodes < 1 or self.jobs < 1:
            raise ValueError(f"--episodes and --jobs must be >= 1, got {self.episodes} and {self.jobs}")


def with_flags(argv: list[str], **flags) -> list[str]:
    """``argv`` with each ``--flag value`` pair of ``flags`` replaced (or added); ``True`` adds a bare flag."""
    out, i = [], 0
    names = {"--" + k.replace("_", "-") for k in flags}
    while i < len(argv):
        if argv[i] in names:
            i += 1
            while i < len(argv) and not argv[i].startswith("--"):
                i += 1
            continue
        out.append(argv[i])
        i += 1
    for key, value in flags.items():
        out += ["--" + key.replace("_", "-")] + ([] if value is True else [str(value)])
    return out


def plan_runs(cfg: FinetuneConfig) -> tuple[dict[str, list[str]], dict[str, tuple[str, str, int]], Path]:
    """The four training commands (by run name), the bench method spec of every point (``spec -> (method, mode,
    step)``, base at step 0) and base's folder."""
    recipe = Recipe.load(cfg.suite, cfg.recipe)
    paths = Paths.default(recipe.suite, cfg.data, cfg.zoo, cfg.out)
    stages = build_stages(recipe, paths)
    base = stages["train_base"].outputs[0]
    commands, points = {}, {"base": ("base", "-", 0)}
    every = cfg.steps // cfg.points
    for method, mode in RUNS:
        name = f"{method}_{mode}"
        out = Path(cfg.out) / name
        extra = {"adapter_only": True} if mode == "adapter" else {}
        commands[name] = with_flags(stages[f"train_{method}"].argv, out=out, steps=cfg.steps, snapshot_every=every,
                                    checkpoint_every=every, **extra)
        for step in range(every, cfg.steps + 1, every):
            points[f"{method}:checkpoint={snapshot_dir(out, step)}"] = (method, mode, step)
    return commands, points, base


def check_inputs(commands: dict[str, list[str]], base: Path, suite: str) -> None:
    """``SystemExit`` naming the zoo command when base or a data file of the build is missing."""
    missing = [] if (base / "model.pt").is_file() else [str(base)]
    for argv in commands.values():
        missing += [p for p in argv[argv.index("--data") + 1].split(",") if not Path(p).is_file()]
    if missing:
        raise SystemExit(f"error: the fine-tuning starts from the zoo build of {suite}; missing: "
                         f"{', '.join(dict.fromkeys(missing))}. Make them with:\n  python -m detaug_gym.zoo build "
                         f"--suite {suite} --stages collect recovery augment_detaug augment_demogen train_base")


def curves(records: list[dict], points: dict[str, tuple[str, str, int]]) -> list[dict]:
    """One row per point: method, mode, step, episodes, success / collision / clean counts and rates (percent)
    with 95 % Wilson intervals. Every episode counts (an errored one is a failure)."""
    from detaug_gym.report import cell_stats, wilson

    rows = []
    for spec, (method, mode, step) in points.items():
        cell = cell_stats([r for r in records if r["method"] == spec])
        row = {"method": method, "mode": mode, "step": step, "n": cell.n, "errors": cell.errors}
        for name, count in (("success", cell.success), ("collision", cell.collision), ("clean", cell.clean)):
            lo, hi = wilson(count, cell.n)
            row |= {name: count, f"{name}_rate": 100 * count / cell.n if cell.n else float("nan"),
                    f"{name}_ci": (lo, hi)}
        rows.append(row)
    return rows


def table(rows: list[dict]) -> str:
    """Markdown: one row per (run, step), base first."""
    lines = ["| run | step | episodes | success % [95 % CI] | collision % [95 % CI] | clean success % |",
             "|---|---:|---:|---:|---:|---:|"]
    for r in rows:
        run = "base" if r["method"] == "base" else f"{r['method']} {r['mode']}"
        cell = [f"{r[m + '_rate']:.1f} [{r[m + '_ci'][0]:.0f}-{r[m + '_ci'][1]:.0f}]" for m in ("success", "collision")]
        lines.append(f"| {run} | {r['step']} | {r['n']}" + (f" ({r['errors']} err.)" if r["errors"] else "")
                     + f" | {cell[0]} | {cell[1]} | {r['clean_rate']:.1f} |")
    return "\n".join(lines)


def plot(rows: list[dict], path: Path, title: str) -> None:
    """Success, collision and clean-success (success without collision) rate over fine-tuning steps (rows),
    adapter-only (left) and full (right), with 95 % Wilson bands; base is the dashed line and every curve's
    step 0."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    base = next(r for r in rows if r["method"] == "base")
    metrics = ("success", "collision", "clean")
    fig, axes = plt.subplots(len(metrics), 2, figsize=(9, 8.5), sharex=True, sharey="row")
    for col, mode in enumerate(("adapter", "full")):
        for row_i, metric in enumerate(metrics):
            ax = axes[row_i, col]
            for method, colour in (("detaug", "tab:blue"), ("demogen", "tab:orange")):
                pts = [base] + sorted((r for r in rows if r["method"] == method and r["mode"] == mode),
                                      key=lambda r: r["step"])
                steps = [p["step"] for p in pts]
                ax.plot(steps, [p[f"{metric}_rate"] for p in pts], "o-", color=colour, label=LABELS[method])
                ax.fill_between(steps, [p[f"{metric}_ci"][0] for p in pts], [p[f"{metric}_ci"][1] for p in pts],
                                color=colour, alpha=0.15)
            ax.axhline(base[f"{metric}_rate"], color="grey", ls="--", lw=1, label="base")
            ax.set_ylim(0, 100)
            ax.grid(alpha=0.3)
            if row_i == 0:
                ax.set_title("adapter only" if mode == "adapter" else "full fine-tune")
            if col == 0:
                ax.set_ylabel("clean success (%)" if metric == "clean" else f"{metric} rate (%)")
            if row_i == len(metrics) - 1:
                ax.set_xlabel("fine-tuning step")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(textwrap.fill(title, 110), fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def run(cfg: FinetuneConfig) -> str:
    """Train, evaluate, then write the table and the figure; returns the table."""
    from detaug_gym.envs.suites import get_suite
    from detaug_gym.pipeline import Task, run_tasks
    from detaug_gym.report import read_records

    commands, points, base = plan_runs(cfg)
    check_inputs(commands, base, cfg.suite)
    out = Path(cfg.out)
    zoo_root = base.parent.parent
    bench = ["--methods", *points, "--suites", cfg.suite, "--levels", cfg.level, "--episodes", str(cfg.episodes),
             "--seeds", str(cfg.seed), "--workers", str(cfg.jobs), "--out", str(out / "bench")]
    tasks = [Task(name, "detaug_gym.train", argv, priority=1.0 if "demogen" in name else 0.0,
                  cores=int(argv[argv.index("--threads") + 1]) if "--threads" in argv else 1)
             for name, argv in commands.items()]
    tasks.append(Task("bench", "detaug_gym.bench", bench, needs=tuple(commands), env={"DETAUG_ZOO": str(zoo_root)},
                      cores=cfg.jobs))
    run_tasks(tasks, cfg.jobs, out / "logs", f"finetune {cfg.suite}")
    rows = curves(read_records(out / "bench" / "episodes.jsonl"), points)
    level = get_suite(cfg.suite).check_level(cfg.level)
    title = (f"{cfg.suite} {level}: {cfg.episodes} episodes per point (the same for every point), "
             f"{cfg.steps} steps; {PAPER}")
    text = (f"# Fine-tuning from the {cfg.suite} base\n\n{title}.\n\n" + table(rows) + "\n\nCommands:\n\n```bash\n"
            + "\n".join(f"python -m detaug_gym.train {' '.join(a)}" for a in commands.values())
            + f"\nDETAUG_ZOO={zoo_root} python -m detaug_gym.bench {' '.join(bench)}\n```\n")
    (out / "finetune.md").write_text(text)
    (out / "curves.json").write_text(json.dumps(rows, indent=1))
    plot(rows, Path(cfg.figure), title)
    return text


def main(argv: list[str] | None = None) -> None:
    try:
        cfg = parse_config(FinetuneConfig, argv, prog="python -m detaug_gym.finetune", description=__doc__)
    except ValueError as exc:
        raise SystemExit(f"error: {exc}") from None
    print(run(cfg))
    print(f"figure: {cfg.figure}")


if __name__ == "__main__":
    main()
