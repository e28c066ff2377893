"""Demonstration datasets: LIBERO/robomimic HDF5 layout, loading (ours and LIBERO's), appending, replay.

>>> from detaug_gym.data import load, replay
>>> dataset = load("data/spatial.hdf5")
>>> states = replay(env, dataset.demos[0])
"""

from detaug_gym.data.dataset import (
    Dataset,
    DatasetError,
    DatasetSummary,
    DatasetWriter,
    Demo,
    load,
    replay,
    summarize,
)

__all__ = ["Dataset", "DatasetError", "DatasetSummary", "DatasetWriter", "Demo", "load", "replay", "summarize"]
