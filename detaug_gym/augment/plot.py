"""The paper's Figure 4 for an augmented dataset: per source demo, the original end-effector path and its
augmented variants in 3D, with the grasp and release windows marked."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from detaug_gym.augment.segment import SegmentConfig, segment_gripper


def group_by_source(demos) -> dict[str, tuple[object, list]]:
    """``source name -> (original demo, [augmented demos])`` in file order."""
    groups: dict[str, tuple[object, list]] = {}
    for d in demos:
        if not d.attrs.get("augmented", False):
            groups.setdefault(str(d.attrs.get("source_demo", d.name)), (d, []))
    for d in demos:
        if d.attrs.get("augmented", False) and str(d.attrs.get("source_demo")) in groups:
            groups[str(d.attrs["source_demo"])][1].append(d)
    return groups


def plot_arcs(demos, path: str | Path, panels: int = 3, variants: int = 6,
              segment: SegmentConfig | None = None) -> Path:
    """Draw up to ``panels`` sources (those with the most accepted variants first) into ``path`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = sorted(group_by_source(demos).values(), key=lambda g: -len(g[1]))[:panels]
    fig = plt.figure(figsize=(5.0 * max(len(groups), 1), 5.0))
    colors = plt.get_cmap("viridis")(np.linspace(0.1, 0.9, variants))
    for k, (orig, augmented) in enumerate(groups):
        ax = fig.add_subplot(1, len(groups), k + 1, projection="3d")
        for color, aug in zip(colors, augmented[:variants]):
            p = aug.obs["eef_pos"]
            ax.plot(p[:, 0], p[:, 1], p[:, 2], color=color, lw=1.2, alpha=0.85)
        p = orig.obs["eef_pos"]
        ax.plot(p[:, 0], p[:, 1], p[:, 2], color="black", lw=2.4, label="original")
        cfg = segment or SegmentConfig()
        seg = segment_gripper(orig.gripper_command, cfg)
        for g in seg.grasps:
            _mark_window(ax, p, g.close, cfg.window, "tab:red", "grasp window")
            # a demo that ends holding (the success check fired on placement) releases at its last frame
            release = g.release if g.release is not None else len(p) - 1
            _mark_window(ax, p, release, cfg.window, "tab:blue", "release window")
        ax.set_title(f"{orig.attrs.get('task_key', orig.name)} ({len(augmented)} variants)", fontsize=9)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_zlabel("z (m)")
        _equal_axes(ax, np.concatenate([p] + [a.obs["eef_pos"] for a in augmented[:variants]]))
        if k == 0:
            handles, labels = ax.get_legend_handles_labels()
            unique = dict(zip(labels, handles))
            ax.legend(unique.values(), unique.keys(), loc="upper left", fontsize=8)
    fig.suptitle("DetAug: transits replaced by arcs (colour), grasp/release windows unchanged", fontsize=11)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _mark_window(ax, path: np.ndarray, frame: int, half: int, color: str, label: str) -> None:
    lo, hi = max(frame - half, 0), min(frame + half, len(path) - 1)
    w = path[lo:hi + 1]
    ax.plot(w[:, 0], w[:, 1], w[:, 2], color=color, lw=5, alpha=0.8, label=label)
    ax.scatter(*path[min(frame, len(path) - 1)], color=color, s=30)


def _equal_axes(ax, points: np.ndarray) -> None:
    centre = 0.5 * (points.max(axis=0) + points.min(axis=0))
    half = 0.5 * float((points.max(axis=0) - points.min(axis=0)).max()) + 0.01
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half, centre[1] + half)
    ax.set_zlim(centre[2] - half, centre[2] + half)
