"""Model cards of the zoo's checkpoints (``README.md`` in each ``policies/<method>/<suite>/``), written by the
``cards`` stage of ``python -m detaug_gym.zoo build`` from what the build left behind: the stages' commands and
times, the data files, the checkpoint's ``config.json`` and the Free evaluation's episodes.

A card states the result against the zoo's bar (base and DetAug at z = 0 solve >= 90 % of what the scripted
expert solves on Free) and by how much it is missed, with sample sizes and 95 % Wilson intervals.
"""

from __future__ import annotations

import json
from pathlib import Path

from detaug_gym.envs.suites import SUITES

TARGET = 0.90  # share of the scripted expert's Free successes base and detaug (z = 0) must reach
DESCRIPTION = {
    "base": "Flow-matching DiT policy (AdaLN-Zero, no label) trained on the scripted expert's clean and recovery "
            "demos. It is the frozen prior that `cape` and `aegis` wrap and the start of the `detaug` and "
            "`demogen` fine-tunes.",
    "detaug": "The same DiT with DetAug's arc label z (phi and theta of the approach and the carry of every grasp) "
              "injected through AdaLN-Zero and a learned null token, fine-tuned from `base` on the DetAug arc "
              "augmentations plus the recovery demos. At test time `make_policy(\"detaug\", suite=...)` samples K "
              "labels per replan, scores the K plans by penetration into the observed obstacle and executes the "
              "best.",
    "demogen": "DemoGen baseline: the DiT plus a DP3-style point-cloud encoder of the obstacle added to the AdaLN "
               "conditioning, fine-tuned from `base` on detours planned around obstacles sampled at training time.",
}
HAS_TARGET = ("base", "detaug")


def _stamp(stage) -> dict:
    try:
        return json.loads(stage.stamp.read_text())
    except (OSError, json.JSONDecodeError):
        return {}


def ancestors(name: str, stages: dict) -> list[str]:
    """``name`` and every stage it depends on, in build order."""
    wanted, todo = set(), [name]
    while todo:
        current = todo.pop()
        if current not in wanted:
            wanted.add(current)
            todo.extend(stages[current].needs)
    return [n for n in stages if n in wanted]


def eval_method(method: str, stages: dict) -> str | None:
    """The ``--methods`` entry of the evaluation that runs ``method`` (``detaug:labels=zero`` for detaug)."""
    argv = stages["evaluate"].argv
    names = argv[argv.index("--methods") + 1: argv.index("--suites")]
    return next((m for m in names if m.split(":")[0] == method), None)


def free_rows(records: list[dict], method: str, suite: str) -> tuple[list[list[str]], tuple[int, int, int]]:
    """Per-task rows ``[task, key, method, scripted]`` and totals ``(method successes, expert successes, n)``."""
    from detaug_gym.report import cell_stats, task_cell

    tasks = SUITES[suite].tasks_for("Free")
    rows, totals = [], [0, 0, 0]
    for index, spec in enumerate(tasks):
        mine = [r for r in records if r["method"] == method and r["task"] == index]
        expert = [r for r in records if r["method"] == "scripted" and r["task"] == index]
        a, b = cell_stats(mine), cell_stats(expert)
        rows.append([str(index), spec.key, task_cell(mine, "Free"), f"{b.success}/{b.n}"])
        totals = [totals[0] + a.success, totals[1] + b.success, totals[2] + a.n]
    return rows, tuple(totals)


def missed(method: str, mine: int, expert: int) -> bool:
    """Whether ``method`` has the zoo's target and misses it."""
    return method in HAS_TARGET and expert > 0 and mine / expert < TARGET


def tried_section(recipe) -> list[str]:
    """The card's lines on what was measured to close a missed target (the recipe's ``tried``)."""
    if not recipe.tried:
        return []
    return [f"What was measured or tried to close it (`{recipe.path.name}`'s `tried`; each measured on the same Free "
            "episodes unless it says otherwise):", "", *(f"- {line}" for line in recipe.tried), ""]


def status(method: str, mine: int, expert: int, n: int) -> str:
    """The card's status line: successes with a Wilson interval, the share of the expert's, and the target."""
    from detaug_gym.report import wilson

    if n == 0:
        return "**Status:** not evaluated (no Free episodes in the build's evaluation)."
    lo, hi = wilson(mine, n)
    line = (f"**Status:** on Free it solves {mine} of {n} episodes ({100 * mine / n:.1f} %, 95 % CI "
            f"{lo:.0f}-{hi:.0f} %); the scripted expert solves {expert} of the same {n}.")
    if method in HAS_TARGET and expert:
        share = mine / expert
        verdict = f"**missed** by {100 * (TARGET - share):.1f} points" if missed(method, mine, expert) else "met"
        line += f" That is {100 * share:.1f} % of the expert; the zoo's target (>= {TARGET:.0%}) is {verdict}."
    return line


def data_rows(train_argv: list[str]) -> list[list[str]]:
    """One row per data file of a training: demos (augmented), steps, per task, and the augmentation's yield."""
    from detaug_gym.augment.runner import progress_path
    from detaug_gym.data import DatasetError, summarize

    rows = []
    for path in map(Path, train_argv[train_argv.index("--data") + 1].split(",")):
        try:
            s = summarize(path)
        except DatasetError as exc:
            rows.append([f"`{path}`", f"unreadable ({exc})", "", "", ""])
            continue
        yield_note = ""
        progress = progress_path(path)
        if progress.is_file():
            p = json.loads(progress.read_text())
            reasons = sorted(p.get("reasons", {}).items(), key=lambda kv: -kv[1])[:4]
            yield_note = (f"{p['accepted']} of {p['requested']} copies requested from {p['sources']} sources "
                          f"({100 * p['accepted'] / max(1, p['tries']):.1f} % of {p['tries']} samples); top "
                          f"rejections: {', '.join(f'{k} {v}' for k, v in reasons) or 'none'}")
        per_task = ", ".join(f"{t}: {c}" for t, c in s.per_task.items())
        rows.append([f"`{path}`", f"{s.demos} ({s.augmented} augmented)", f"{s.steps:,}", per_task, yield_note])
    return rows


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join([*lines, *("| " + " | ".join(r) + " |" for r in rows)])


def card(method: str, train_stage: str, stages: dict, recipe, paths) -> str:
    """The model card of the checkpoint ``train_stage`` built (markdown)."""
    from detaug_gym.report import read_records

    folder = stages[train_stage].outputs[0]
    config = json.loads((folder / "config.json").read_text())
    summary, train = config.get("summary", {}), config.get("train", {})
    suite = recipe.suite
    records = read_records(paths.work / "free" / "episodes.jsonl")
    name = eval_method(method, stages)
    rows, (mine, expert, n) = free_rows(records, name, suite) if name else ([], (0, 0, 0))
    commands = []
    for stage_name in ancestors(train_stage, stages):
        st = _stamp(stages[stage_name])
        took = f"  # {st['seconds'] / 60:.1f} min" if "seconds" in st else ""
        commands.append(stages[stage_name].command() + took)
    size = (folder / "model.pt").stat().st_size / 1e6 if (folder / "model.pt").exists() else float("nan")
    training = [
        ["init", f"`{train['init_from']}`" if train.get("init_from") else "random"],
        ["optimiser", f"AdamW {train.get('lr')}, {train.get('warmup_steps')} warmup + cosine, batch "
                      f"{train.get('batch_size')}, EMA {train.get('ema_decay')}, {train.get('steps')} steps, "
                      f"{train.get('threads')} torch thread(s), seed {train.get('seed')}"],
        ["wall time", f"{summary.get('wall_time_s', float('nan')):,.0f} s ({summary.get('step_time_s', float('nan'))}"
                      " s/step)"],
        ["final loss", f"{summary.get('final_loss', float('nan')):.4f} (EMA model)"],
        ["parameters", f"{summary.get('parameters', config.get('parameters', 0)):,}; `model.pt` {size:.1f} MB"],
        ["replans", f"every {config.get('policy', {}).get('action_steps', '?')} steps (`config.json` -> policy)"],
    ]
    evaluation = stages["evaluate"].command()
    parts = [
        f"# {method} / {suite}",
        "",
        DESCRIPTION[method],
        "",
        status(method, mine, expert, n),
        "",
        *(tried_section(recipe) if missed(method, mine, expert) else []),
        f"Built by `python -m detaug_gym.zoo build --suite {suite}` from `{recipe.path.name}` "
        f"(`policies/recipes/`); this card is written by its `cards` stage. Load it with "
        f"`make_policy(\"{method}\", suite=\"{suite}\")`.",
        "",
        "## Commands",
        "",
        "```bash",
        *commands,
        "```",
        "",
        "## Data",
        "",
        _table(["file", "demos", "steps", "demos per task", "augmentation"], data_rows(stages[train_stage].argv)),
        "",
        "## Training",
        "",
        _table(["item", "value"], training),
        "",
        "## Measured",
        "",
        f"Free, {n} episodes (the same for every method of the build):",
        "",
        "```bash",
        evaluation,
        "```",
        "",
        _table(["task", "key", name or method, "scripted"], rows) if rows else "(no episodes)",
        "",
        "Obstacle levels: `python -m detaug_gym.bench --methods ... --suites " + suite + " --levels 1 2` "
        "(`docs/results.md`).",
        "",
    ]
    return "\n".join(parts)
