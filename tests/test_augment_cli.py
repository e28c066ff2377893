"""``python -m detaug_gym.augment`` refuses bad files with a one-line error (no simulator needed) and keeps its
mode registry lazy."""

from __future__ import annotations

import subprocess
import sys

import pytest

from detaug_gym.augment.__main__ import main as augment_main
from detaug_gym.data import DatasetWriter

ENV_ARGS = {"env_name": "SafeLibero-Spatial-Free-v0", "env_version": "0", "type": "detaug_gym", "env_kwargs": {}}


def _refusal(argv: list[str]) -> str:
    with pytest.raises(SystemExit) as exc:
        augment_main(argv + ["--copies", "1", "--no-progress"])
    message = str(exc.value)
    assert message.startswith("error: ") and "\n" not in message, message
    return message


@pytest.fixture
def empty(tmp_path):
    """A dataset file without demos."""
    path = tmp_path / "empty.hdf5"
    with DatasetWriter(path, ENV_ARGS):
        pass
    return path


def test_out_equal_to_in_is_refused(empty):
    before = empty.read_bytes()
    message = _refusal(["--in", str(empty), "--out", str(empty.parent / "." / empty.name)])
    assert "modify its source" in message
    assert empty.read_bytes() == before


def test_a_file_without_demos_is_refused(empty, tmp_path):
    message = _refusal(["--in", str(empty), "--out", str(tmp_path / "out.hdf5")])
    assert "empty.hdf5: no demos to augment" in message
    assert not (tmp_path / "out.hdf5").exists()


@pytest.mark.parametrize("mode", ["detaug", "demogen"])
def test_a_corrupt_existing_out_is_refused(empty, tmp_path, mode):
    out = tmp_path / "out.hdf5"
    out.write_bytes(b"not hdf5 at all")
    message = _refusal(["--mode", mode, "--in", str(empty), "--out", str(out)])
    assert "out.hdf5: cannot resume, not a readable HDF5 file" in message
    assert out.read_bytes() == b"not hdf5 at all"


def test_modes_load_lazily_by_name():
    code = ("import sys; from detaug_gym.augment.runner import load_mode; "
            "assert not any(m.endswith(('.detaug', '.demogen')) for m in sys.modules); "
            "mode = load_mode('detaug'); assert mode.name == 'detaug' and mode.label_size.__self__ is mode; "
            "assert 'detaug_gym.augment.demogen' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)
    from detaug_gym.augment.runner import load_mode

    with pytest.raises(ValueError, match="valid modes: detaug, demogen"):
        load_mode("nope")
