"""Tables, plots and a LeRobot-style ``eval_info.json`` computed from the bench's episode lines (the paper's
Table I layout), with sample sizes and uncertainty beside every rate.

Every episode of a cell counts, errored ones included: an error is a failure in Clean and Total, and counts in
Avoid by whether the obstacle had been hit before the error. Rates come with a 95 % Wilson interval over the
cell's episodes; with several run seeds (``--seeds``) the tables also give mean ± std over the seeds.
"""

from __future__ import annotations

import csv
import json
import math
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from detaug_gym.envs.suites import SUITES

SUITE_ORDER = tuple(SUITES)
METRICS = ("Clean", "Total", "Avoid", "Timeout")
Z95 = 1.959963984540054
CAPTION = ("Clean = success without collision, Total = success irrespective of collision, Avoid = 1 - collision "
           "rate, Timeout = episodes that hit the step limit, ETS = mean episode steps. Every episode counts: an "
           "episode that errored is a failure in Clean and Total and counts in Avoid by whether the obstacle had "
           "been hit before the error. 95 % Wilson intervals over the episodes; with several run seeds, "
           "mean ± std over the seeds.")


# The DetAug paper's Table I (official SafeLIBERO, feasible cells, levels averaged; Clean / Total / Avoid, percent).
PAPER_TABLE_I = {
    "spatial": {"detaug": (58.7, 73.0, 68.0), "cape": (42.0, 46.7, 71.2), "aegis": (28.1, 43.0, 57.1),
                "demogen": (19.4, 51.7, 24.5)},
    "object": {"detaug": (88.5, 92.5, 94.0), "cape": (52.2, 57.1, 87.2), "aegis": (47.2, 60.6, 67.2),
               "demogen": (32.4, 80.7, 33.5)},
    "goal": {"detaug": (32.5, 58.0, 43.5), "cape": (25.8, 37.2, 61.2), "aegis": (17.2, 24.2, 59.3),
             "demogen": (22.5, 56.8, 24.8)},
    "long": {"detaug": (29.1, 46.9, 56.0), "cape": (2.2, 3.0, 79.0), "aegis": (13.8, 15.6, 73.0),
             "demogen": (7.0, 30.2, 22.4)},
}


def paper_rows(summary) -> tuple[list[str], list[list[str]]]:
    """Our Clean / Total / Avoid per (method, suite) beside the paper's, for the methods and suites it reports."""
    header = ["Method", "Suite"] + [f"{m} ({who})" for m in METRICS[:3] for who in ("ours", "paper")]
    rows = []
    for method in sorted({k[0] for k in summary}):
        for suite, reported in PAPER_TABLE_I.items():
            paper = reported.get(method.split(":")[0])
            cells = [v for k, v in summary.items() if k[0] == method and k[1] == suite]
            if paper is None or not cells:
                continue
            ours = [_group_rate(cells, m)[0] for m in METRICS[:3]]
            rows.append([method, suite] + [x for o, p in zip(ours, paper) for x in (_fmt(o), f"{p:.1f}")])
    return header, rows


def read_records(path: Path) -> list[dict]:
    """All episode lines of a JSONL file; a later line for the same episode supersedes an earlier one (a
    retried error), and a line that does not parse (torn by a crash; :func:`repair_log` removes it) is skipped."""
    if not path.exists():
        return []
    latest: dict[tuple, dict] = {}
    for line in path.read_text().splitlines():
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            continue
        latest[record_key(record)] = record
    return list(latest.values())


def record_key(record: dict) -> tuple:
    """What identifies an episode line: (method, env id, task, episode, episode seed)."""
    return (record.get("method"), record.get("env_id"), record.get("task"), record.get("episode"), record.get("seed"))


def repair_log(path: Path) -> int:
    """Drop lines of ``path`` that do not parse as JSON (a line torn by a crash mid-write) and make the file end
    with a newline; returns how many lines were dropped. The file is rewritten atomically."""
    if not path.exists():
        return 0
    text = path.read_text()
    lines = text.splitlines()
    good = []
    for line in lines:
        try:
            json.loads(line)
            good.append(line)
        except json.JSONDecodeError:
            continue
    dropped = len(lines) - len(good)
    if dropped or (text and not text.endswith("\n")):
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_text("".join(line + "\n" for line in good))
        tmp.replace(path)
    return dropped


def wilson(successes: int, n: int, z: float = Z95) -> tuple[float, float]:
    """95 % Wilson score interval (percent) of ``successes`` out of ``n``; (nan, nan) for n = 0."""
    if n == 0:
        return float("nan"), float("nan")
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return 100 * max(0.0, centre - half), 100 * min(1.0, centre + half)


@dataclass
class Cell:
    """Counts of one (method, suite, level) cell, and the same per run seed."""

    n: int
    clean: int
    success: int
    collision: int
    timeout: int
    errors: int
    steps: float
    has_obstacle: bool
    per_seed: dict[int, Cell] | None = None

    def rate(self, metric: str) -> float:
        """Percent of the cell's episodes (NaN when undefined: no episode, or Avoid without an obstacle)."""
        if self.n == 0 or (metric == "Avoid" and not self.has_obstacle):
            return float("nan")
        count = {"Clean": self.clean, "Total": self.success, "Avoid": self.n - self.collision,
                 "Timeout": self.timeout, "Errors": self.errors}[metric]
        return 100.0 * count / self.n

    def interval(self, metric: str) -> tuple[float, float]:
        if metric == "Avoid" and not self.has_obstacle:
            return float("nan"), float("nan")
        count = {"Clean": self.clean, "Total": self.success, "Avoid": self.n - self.collision,
                 "Timeout": self.timeout}[metric]
        return wilson(count, self.n)

    def seed_std(self, metric: str) -> float:
        """Std over run seeds of the rate (NaN with fewer than two seeds)."""
        if not self.per_seed or len(self.per_seed) < 2:
            return float("nan")
        return float(np.std([c.rate(metric) for c in self.per_seed.values()], ddof=1))


def succeeded(record: dict) -> bool:
    """The task done (an errored episode never counts as done)."""
    return bool(record.get("success")) and record.get("termination") != "error"


def clean(record: dict) -> bool:
    """The task done without a collision."""
    return succeeded(record) and not record.get("collision")


def avoided(record: dict) -> bool:
    """The obstacle never moved."""
    return not record.get("collision")


def _count(records: list[dict]) -> Cell:
    n = len(records)
    success = [succeeded(r) for r in records]
    collision = [bool(r.get("collision")) for r in records]
    return Cell(
        n=n,
        clean=sum(s and not c for s, c in zip(success, collision)),
        success=sum(success),
        collision=sum(collision),
        timeout=sum(r.get("termination") == "timeout" for r in records),
        errors=sum(r.get("termination") == "error" for r in records),
        steps=float(np.mean([r.get("steps", 0) for r in records])) if records else float("nan"),
        has_obstacle=bool(records) and records[0].get("level") != "Free",
    )


def cell_stats(records: list[dict]) -> Cell:
    """The :class:`Cell` of one group of episode lines (its ``per_seed`` split by ``run_seed``)."""
    cell = _count(records)
    by_seed: dict[int, list[dict]] = defaultdict(list)
    for r in records:
        by_seed[int(r.get("run_seed", 0))].append(r)
    cell.per_seed = {seed: _count(rs) for seed, rs in sorted(by_seed.items())}
    return cell


def summarise(records: list[dict]) -> dict[tuple[str, str, str], Cell]:
    """A :class:`Cell` per (method, suite, level)."""
    groups: dict[tuple[str, str, str], list[dict]] = defaultdict(list)
    for r in records:
        groups[(r["method"], r["suite"], r["level"])].append(r)
    return {key: cell_stats(rs) for key, rs in groups.items()}


def _fmt(value: float) -> str:
    return "-" if value != value else f"{value:.1f}"


def _fmt_std(value: float, std: float) -> str:
    return _fmt(value) if std != std or value != value else f"{value:.1f} ± {std:.1f}"


def _ci(lo: float, hi: float) -> str:
    return "-" if lo != lo else f"[{lo:.0f}, {hi:.0f}]"


def _mean(values: list[float]) -> float:
    """Mean over the defined values; NaN (shown as "-") when none is, e.g. Avoid on the obstacle-free level."""
    defined = [v for v in values if v == v]
    return float(np.mean(defined)) if defined else float("nan")


def _group_rate(cells: list[Cell], metric: str) -> tuple[float, float]:
    """Mean over ``cells`` (levels or suites) of the rate, and its std over run seeds (each seed's mean)."""
    value = _mean([c.rate(metric) for c in cells])
    seeds = sorted({s for c in cells for s in (c.per_seed or {})})
    if len(seeds) < 2:
        return value, float("nan")
    per_seed = [_mean([c.per_seed[s].rate(metric) for c in cells if s in (c.per_seed or {})]) for s in seeds]
    defined = [v for v in per_seed if v == v]
    return value, float(np.std(defined, ddof=1)) if len(defined) > 1 else float("nan")


def table_rows(summary) -> tuple[list[str], list[list[str]]]:
    """Rows of the Table I layout: per method, per suite Clean/Total/Avoid averaged over levels, then Average,
    the errored episodes and the episode count."""
    methods = sorted({k[0] for k in summary})
    suites = [s for s in SUITE_ORDER if any(k[1] == s for k in summary)]
    header = ["Method"] + [f"{s.capitalize()} {m}" for s in suites for m in METRICS[:3]]
    header += [f"Average {m}" for m in METRICS] + ["Errors", "Episodes"]
    rows = []
    for method in methods:
        row, all_cells = [method], []
        for suite in suites:
            cells = [v for k, v in summary.items() if k[0] == method and k[1] == suite]
            all_cells += cells
            row += [_fmt_std(*_group_rate(cells, m)) for m in METRICS[:3]]
        suite_cells = [[v for k, v in summary.items() if k[0] == method and k[1] == s] for s in suites]
        for m in METRICS:
            per_suite = [_group_rate(cells, m)[0] for cells in suite_cells if cells]
            row.append(_fmt(_mean(per_suite)))
        row += [str(sum(c.errors for c in all_cells)), str(sum(c.n for c in all_cells))]
        rows.append(row)
    return header, rows


def level_rows(summary) -> tuple[list[str], list[list[str]]]:
    """One row per (method, suite, level): every metric with its 95 % interval, errors, ETS and sample sizes."""
    header = ["Method", "Suite", "Level"]
    for m in METRICS[:3]:
        header += [m, f"{m} 95% CI"]
    header += ["Timeout", "Errors", "ETS", "Episodes", "Seeds"]
    rows = []
    for (m, s, lv), cell in sorted(summary.items()):
        row = [m, s, lv]
        for metric in METRICS[:3]:
            row += [_fmt_std(cell.rate(metric), cell.seed_std(metric)), _ci(*cell.interval(metric))]
        row += [_fmt(cell.rate("Timeout")), str(cell.errors), _fmt(cell.steps), str(cell.n),
                str(len(cell.per_seed or {}))]
        rows.append(row)
    return header, rows


def task_cell(records: list[dict], level: str) -> str:
    """``"9/20 (3 coll., 1 err., 1.4 of 2 goals)"``: one method's successes over its episodes of one task, with
    its collisions (not on Free), errors, and for a task of several sub-goals the mean of the most of them met at
    one step (records written before the bench kept ``goals`` have none); ``"-"`` without episodes."""
    c = _count(records)
    if not c.n:
        return "-"
    notes = ([f"{c.collision} coll."] if level != "Free" else []) + ([f"{c.errors} err."] if c.errors else [])
    several = [r for r in records if (r.get("goals") or 0) > 1]
    if several:
        notes.append(f"{_mean([r['goals_met'] for r in several]):.1f} of {max(r['goals'] for r in several)} goals")
    return f"{c.success}/{c.n}" + (f" ({', '.join(notes)})" if notes else "")


def task_rows(records: list[dict]) -> tuple[list[str], list[list[str]]]:
    """One row per (suite, level, task): :func:`task_cell` per method."""
    groups: dict[tuple, dict[str, list[dict]]] = defaultdict(lambda: defaultdict(list))
    for r in records:
        groups[(r["suite"], r["level"], r["task"])][r["method"]].append(r)
    methods = sorted({r["method"] for r in records})
    header = ["Suite", "Level", "Task", *methods]
    rows = []
    for (suite, level, task), by_method in sorted(groups.items()):
        rows.append([suite, level, str(task), *(task_cell(by_method.get(m, []), level) for m in methods)])
    return header, rows


def collision_rows(records: list[dict], by: str) -> tuple[list[str], list[list[str]]]:
    """Collided episodes per (method, suite, level), split by their ``collision_cause[by]`` (``"body"``: which
    kind of body moved the obstacle; ``"phase"``: approach / grasp / carry / release / retreat). Records
    from before the attribution count as ``unattributed``; errored episodes are left out, as in Table I."""
    groups: dict[tuple, list[str]] = defaultdict(list)
    for r in records:
        if r.get("collision") and r.get("termination") != "error":
            cause = r.get("collision_cause") or {}
            groups[(r["method"], r["suite"], r["level"])].append(str(cause.get(by, "unattributed")))
    values = sorted({v for vs in groups.values() for v in vs})
    header = ["Method", "Suite", "Level", "Collisions", *values]
    rows = [[m, suite, level, str(len(vs)), *(str(vs.count(v)) for v in values)]
            for (m, suite, level), vs in sorted(groups.items())]
    return header, rows


def sign_test(wins: int, losses: int) -> float:
    """Exact two-sided sign test: the probability, under a fair coin over the ``wins + losses`` episodes where
    two methods differ, of a split at least this uneven (ties, episodes where they agree, carry no weight)."""
    n = wins + losses
    if n == 0:
        return 1.0
    tail = sum(math.comb(n, k) for k in range(min(wins, losses) + 1)) / 2.0 ** n
    return min(1.0, 2.0 * tail)


def paired_rows(records: list[dict]) -> tuple[list[str], list[list[str]]]:
    """Every method against the method of highest mean Clean, on the episodes both ran (same suite, level, run
    seed and episode index, hence the same init and obstacle): episodes shared, then per outcome (Clean,
    Avoid) the episodes only the leader got right, only the other got right, and the sign test's p. A
    difference of rates without this pairing hides how many episodes actually moved."""
    by_method: dict[str, dict[tuple, dict]] = defaultdict(dict)
    for r in records:
        if r.get("level") != "Free":
            by_method[r["method"]][(r["suite"], r["level"], r.get("run_seed", 0), r["episode"])] = r
    if len(by_method) < 2:
        return [], []
    leader = max(sorted(by_method), key=lambda m: _mean([clean(r) for r in by_method[m].values()]))
    header = ["Method", "Against", "Episodes", "Clean: leader only", "Clean: method only", "Clean p",
              "Avoid: leader only", "Avoid: method only", "Avoid p"]
    rows = []
    for method in sorted(by_method):
        if method == leader:
            continue
        shared = sorted(by_method[leader].keys() & by_method[method].keys())
        row = [method, leader, str(len(shared))]
        for outcome in (clean, avoided):
            ahead = sum(outcome(by_method[leader][k]) and not outcome(by_method[method][k]) for k in shared)
            behind = sum(outcome(by_method[method][k]) and not outcome(by_method[leader][k]) for k in shared)
            p = sign_test(ahead, behind)
            row += [str(ahead), str(behind), f"{p:.3f}" if p >= 0.001 else "<0.001"]
        rows.append(row)
    return header, rows


def markdown(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def eval_info(records: list[dict]) -> dict:
    """LeRobot's eval schema: ``per_episode``, ``per_task`` (one entry per method x env x task),
    ``per_group`` (per method x env), ``overall`` (per method), each with ``pc_success`` and the sums of rewards
    (reward here = success, as LeRobot's LIBERO envs report it), plus our obstacle fields."""
    def agg(rs: list[dict]) -> dict:
        succ = [bool(r.get("success")) and r.get("termination") != "error" for r in rs]
        return {"avg_sum_reward": float(np.mean(succ)) if rs else float("nan"),
                "avg_max_reward": float(np.mean(succ)) if rs else float("nan"),
                "pc_success": 100.0 * float(np.mean(succ)) if rs else float("nan"),
                "pc_collision": 100.0 * float(np.mean([bool(r.get("collision")) for r in rs])) if rs else float("nan"),
                "n_episodes": len(rs), "n_errors": sum(r.get("termination") == "error" for r in rs),
                "eval_s": float(sum(r.get("wall_time", 0.0) for r in rs)),
                "eval_ep_s": float(np.mean([r.get("wall_time", 0.0) for r in rs])) if rs else float("nan")}

    per_episode = [{"method": r["method"], "task_group": r["env_id"], "task_id": r["task"],
                    "episode_ix": r["episode"], "seed": r["seed"], "run_seed": r.get("run_seed", 0),
                    "sum_reward": float(bool(r.get("success"))), "max_reward": float(bool(r.get("success"))),
                    "success": bool(r.get("success")), "collision": bool(r.get("collision")),
                    "termination": r.get("termination"), "steps": r.get("steps"), "video_path": r.get("video")}
                   for r in sorted(records, key=record_key)]
    tasks: dict[tuple, list[dict]] = defaultdict(list)
    groups: dict[tuple, list[dict]] = defaultdict(list)
    methods: dict[str, list[dict]] = defaultdict(list)
    for r in records:
        tasks[(r["method"], r["env_id"], r["task"])].append(r)
        groups[(r["method"], r["env_id"])].append(r)
        methods[r["method"]].append(r)
    return {
        "per_episode": per_episode,
        "per_task": [{"method": m, "task_group": g, "task_id": t, "metrics": agg(rs)}
                     for (m, g, t), rs in sorted(tasks.items())],
        "per_group": {f"{m}/{g}": agg(rs) for (m, g), rs in sorted(groups.items())},
        "overall": {m: agg(rs) for m, rs in sorted(methods.items())},
    }


def write_report(records: list[dict], out: Path, notes: tuple[str, ...] = (), beside_paper: bool = False) -> str:
    """Write ``table.md``, ``table.csv``, ``levels.csv``, ``tasks.csv``, ``paired.csv``, ``collisions_body.csv``,
    ``collisions_phase.csv``, ``eval_info.json`` and ``results.png``
    into ``out``; return the Markdown. ``notes`` extend the caption (which scenarios, which cells were left
    out); ``beside_paper`` adds the paper's Table I numbers next to ours (meaningful on official scenarios)."""
    summary = summarise(records)
    header, rows = table_rows(summary)
    lheader, lrows = level_rows(summary)
    theader, trows = task_rows(records)
    bheader, brows = collision_rows(records, "body")
    phheader, phrows = collision_rows(records, "phase")
    paheader, parows = paired_rows(records)
    text = (
        "## Table I (percent; averaged over levels within a suite)\n\n" + markdown(header, rows)
        + "\n\n" + " ".join((CAPTION, *notes)) + "\n\n"
    )
    pheader, prows = paper_rows(summary) if beside_paper else ([], [])
    if prows:
        text += ("## Beside the paper (DetAug, Table I: official SafeLIBERO)\n\n" + markdown(pheader, prows)
                 + "\n\n")
    text += ("## Per level\n\n" + markdown(lheader, lrows) + "\n\n"
             "## Per task (successes / episodes)\n\n" + markdown(theader, trows) + "\n")
    if parows:
        text += ("\n## Paired against the leader (the same episodes; sign test over those that differ)\n\n"
                 + markdown(paheader, parows) + "\n")
    if brows:
        text += ("\n## Collisions by body (what moved the obstacle first)\n\n" + markdown(bheader, brows) + "\n\n"
                 "## Collisions by phase\n\n" + markdown(phheader, phrows) + "\n")
    (out / "table.md").write_text(text)
    for name, (h, r) in {"table.csv": (header, rows), "levels.csv": (lheader, lrows),
                         "tasks.csv": (theader, trows), "paired.csv": (paheader, parows),
                         "collisions_body.csv": (bheader, brows),
                         "collisions_phase.csv": (phheader, phrows)}.items():
        with open(out / name, "w", newline="") as f:
            csv.writer(f).writerows([h, *r])
    (out / "eval_info.json").write_text(json.dumps(eval_info(records), indent=1, allow_nan=True))
    _plot(summary, out / "results.png")
    return text


def _plot(summary, path: Path) -> None:
    """Bars per (suite, level) cell and method; error bars: std over seeds when there are several, else the
    Wilson interval."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cells = sorted({(k[1], k[2]) for k in summary})
    methods = sorted({k[0] for k in summary})
    fig, axes = plt.subplots(1, 3, figsize=(4 + 1.2 * len(cells) * 3, 3.6), sharey=True)
    width = 0.8 / max(len(methods), 1)
    x = np.arange(len(cells))
    for ax, metric in zip(axes, METRICS[:3]):
        for i, method in enumerate(methods):
            values, errors = [], [[], []]
            for s, lv in cells:
                cell = summary.get((method, s, lv))
                value = cell.rate(metric) if cell else float("nan")
                std = cell.seed_std(metric) if cell else float("nan")
                lo, hi = (value - std, value + std) if std == std else (cell.interval(metric) if cell else (value,) * 2)
                values.append(value)
                errors[0].append(0.0 if value != value or lo != lo else max(0.0, value - lo))
                errors[1].append(0.0 if value != value or hi != hi else max(0.0, hi - value))
            ax.bar(x + i * width, np.nan_to_num(values), width, yerr=errors, capsize=2, label=method)
        ax.set_xticks(x + 0.4 - width / 2, [f"{s}\n{lv}" for s, lv in cells])
        ax.set_title(metric)
        ax.set_ylim(0, 105)
    axes[0].set_ylabel("% (error bars: std over seeds, else 95 % Wilson)")
    axes[-1].legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
