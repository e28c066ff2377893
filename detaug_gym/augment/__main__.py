"""Augment a demonstration file: ``python -m detaug_gym.augment``.

    python -m detaug_gym.augment --in data/spatial.hdf5 --out data/spatial_detaug.hdf5 --copies 8
    python -m detaug_gym.augment --in data/spatial.hdf5 --out data/spatial_detaug.hdf5 --copies 8 \\
        --plot docs/detaug_arcs.png
    python -m detaug_gym.augment --in data/goal.hdf5 --out data/goal_detaug.hdf5 --phi 0.15 0.85 --tries 6

Writes the originals (label = zeros) and the accepted augmented demos (label, source_demo, phi/theta per
transit, augmentation parameters) in the input's HDF5 layout; re-running the same command resumes.
``--mode`` picks the augmentation (``detaug``, the default); its options are listed under its name, the
options every mode shares under "every mode".
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from detaug_gym.augment import engine
from detaug_gym.augment.runner import MODES, RunArgs, load_mode, run
from detaug_gym.data.dataset import DatasetError


def build_parser(mode: str) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m detaug_gym.augment", description=__doc__.split("\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--in", dest="inp", required=True, help="input demonstrations (HDF5)")
    parser.add_argument("--out", required=True, help="output HDF5 (resumed if it exists)")
    parser.add_argument("--copies", type=int, default=8, help="augmented copies wanted per demo (default 8)")
    parser.add_argument("--mode", default="detaug", choices=sorted(MODES), help="augmentation (default detaug)")
    parser.add_argument("--seed", type=int, default=0, help="base seed (default 0)")
    parser.add_argument("--limit", type=int, default=None,
                        help="augment only N source demos, taken task by task in turn (first demo of every "
                             "task, then the second, ...)")
    parser.add_argument("--plot", default=None, metavar="FILE.png",
                        help="also draw original and augmented eef paths of a few demos (paper Fig. 4)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    engine.add_arguments(parser)
    load_mode(mode).add_arguments(parser.add_argument_group(mode))
    return parser


def main(argv: list[str] | None = None) -> None:
    import torch

    torch.set_num_threads(1)  # shared machine: torch threads stall under load
    argv = sys.argv[1:] if argv is None else argv
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--mode", default="detaug")
    mode_name = pre.parse_known_args(argv)[0].mode
    if mode_name not in MODES:
        raise SystemExit(f"error: unknown --mode {mode_name!r}; valid: {', '.join(sorted(MODES))}")
    ns = build_parser(mode_name).parse_args(argv)
    if ns.copies < 0:
        raise SystemExit("error: --copies must be >= 0")
    if not Path(ns.inp).exists():
        raise SystemExit(f"error: --in {ns.inp}: no such file")
    args = RunArgs(inp=Path(ns.inp), out=Path(ns.out), copies=ns.copies, mode=mode_name,
                   config=engine.make_config(load_mode(mode_name), ns), seed=ns.seed, limit=ns.limit)
    start = time.perf_counter()
    try:
        stats = run(args, progress=not ns.no_progress)
    except DatasetError as exc:
        raise SystemExit(f"error: {exc}") from None
    print(stats.report())
    print(f"wrote {args.out} in {time.perf_counter() - start:.0f} s")
    if ns.plot:
        from detaug_gym.augment.plot import plot_arcs
        from detaug_gym.data import load

        print(f"figure: {plot_arcs(load(args.out).demos, ns.plot)}")


if __name__ == "__main__":
    main()
