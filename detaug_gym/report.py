"""Tables and plots computed from the bench's episode lines (the paper's Table I layout)."""

from __future__ import annotations

import csv
import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from detaug_gym.envs.suites import SUITES

SUITE_ORDER = tuple(SUITES)
METRICS = ("Clean", "Total", "Avoid", "Timeout")


def read_records(path: Path) -> list[dict]:
    """All episode lines of a JSONL file (a truncated last line, from a killed run, is skipped)."""
    if not path.exists():
        return []
    records = []
    for line in path.read_text().splitlines():
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return records


def cell_metrics(records: list[dict]) -> dict[str, float]:
    """Clean (success without collision), Total (success), Avoid (1 - collision rate), Timeout, in %."""
    ok = [r for r in records if r["termination"] != "error"]
    if not ok:
        return {m: float("nan") for m in METRICS} | {"n": 0, "errors": len(records)}
    success = np.array([r["success"] for r in ok], dtype=float)
    collision = np.array([r["collision"] for r in ok], dtype=float)
    has_obstacle = ok[0]["level"] != "Free"
    return {
        "Clean": 100 * float(np.mean(success * (1 - collision))),
        "Total": 100 * float(np.mean(success)),
        "Avoid": 100 * float(1 - np.mean(collision)) if has_obstacle else float("nan"),
        "Timeout": 100 * float(np.mean([r["termination"] == "timeout" for r in ok])),
        "n": len(ok),
        "errors": len(records) - len(ok),
    }


def summarise(records: list[dict]) -> dict[tuple[str, str, str], dict[str, float]]:
    """Metrics per (method, suite, level)."""
    groups: dict[tuple[str, str, str], list[dict]] = defaultdict(list)
    for r in records:
        groups[(r["method"], r["suite"], r["level"])].append(r)
    return {key: cell_metrics(rs) for key, rs in groups.items()}


def _fmt(value: float) -> str:
    return "-" if value != value else f"{value:.1f}"


def _mean(values: list[float]) -> float:
    """Mean over the defined values; NaN (shown as "-") when none is, e.g. Avoid on the obstacle-free level."""
    defined = [v for v in values if v == v]
    return float(np.mean(defined)) if defined else float("nan")


def table_rows(summary) -> tuple[list[str], list[list[str]]]:
    """Rows of the Table I layout: per method, per suite Clean/Total/Avoid averaged over levels, then Average."""
    methods = sorted({k[0] for k in summary})
    suites = [s for s in SUITE_ORDER if any(k[1] == s for k in summary)]
    header = ["Method"] + [f"{s.capitalize()} {m}" for s in suites for m in METRICS[:3]]
    header += [f"Average {m}" for m in METRICS]
    rows = []
    for method in methods:
        row, per_suite = [method], []
        for suite in suites:
            cells = [v for k, v in summary.items() if k[0] == method and k[1] == suite]
            means = {m: _mean([c[m] for c in cells]) for m in METRICS}
            per_suite.append(means)
            row += [_fmt(means[m]) for m in METRICS[:3]]
        row += [_fmt(_mean([p[m] for p in per_suite])) for m in METRICS]
        rows.append(row)
    return header, rows


def level_rows(summary) -> tuple[list[str], list[list[str]]]:
    """One row per (method, suite, level) with all metrics and episode counts."""
    header = ["Method", "Suite", "Level", *METRICS, "Episodes", "Errors"]
    rows = [[m, s, lv] + [_fmt(v[k]) for k in METRICS] + [str(v["n"]), str(v["errors"])]
            for (m, s, lv), v in sorted(summary.items())]
    return header, rows


def task_rows(records: list[dict]) -> tuple[list[str], list[list[str]]]:
    """One row per (suite, level, task): ``successes/episodes`` (collisions in brackets) for every method."""
    counts: dict[tuple, dict[str, list[int]]] = defaultdict(lambda: defaultdict(lambda: [0, 0, 0]))
    for r in records:
        if r["termination"] == "error":
            continue
        c = counts[(r["suite"], r["level"], r["task"])][r["method"]]
        c[0] += bool(r["success"])
        c[1] += bool(r["collision"])
        c[2] += 1
    methods = sorted({r["method"] for r in records})
    header = ["Suite", "Level", "Task", *methods]
    rows = []
    for (suite, level, task), by_method in sorted(counts.items()):
        cells = []
        for m in methods:
            s, col, n = by_method.get(m, (0, 0, 0))
            cells.append("-" if not n else f"{s}/{n}" + (f" ({col} coll.)" if level != "Free" else ""))
        rows.append([suite, level, str(task), *cells])
    return header, rows


def markdown(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def write_report(records: list[dict], out: Path) -> str:
    """Write ``table.md``, ``table.csv``, ``levels.csv``, ``tasks.csv`` and ``results.png`` into ``out``;
    return the Markdown."""
    summary = summarise(records)
    header, rows = table_rows(summary)
    lheader, lrows = level_rows(summary)
    theader, trows = task_rows(records)
    text = (
        "## Table I (percent; averaged over levels within a suite)\n\n" + markdown(header, rows)
        + "\n\nClean = success without collision, Total = success irrespective of collision, "
        "Avoid = 1 - collision rate, Timeout = episodes that hit the step limit.\n\n"
        "## Per level\n\n" + markdown(lheader, lrows) + "\n\n"
        "## Per task (successes / episodes)\n\n" + markdown(theader, trows) + "\n"
    )
    (out / "table.md").write_text(text)
    for name, (h, r) in {"table.csv": (header, rows), "levels.csv": (lheader, lrows),
                         "tasks.csv": (theader, trows)}.items():
        with open(out / name, "w", newline="") as f:
            csv.writer(f).writerows([h, *r])
    _plot(summary, out / "results.png")
    return text


def _plot(summary, path: Path) -> None:
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
            values = [summary.get((method, s, lv), {}).get(metric, np.nan) for s, lv in cells]
            ax.bar(x + i * width, np.nan_to_num(values), width, label=method)
        ax.set_xticks(x + 0.4 - width / 2, [f"{s}\n{lv}" for s, lv in cells])
        ax.set_title(metric)
        ax.set_ylim(0, 100)
    axes[0].set_ylabel("%")
    axes[-1].legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
