"""Episode videos: a rollout hook that renders every step (the env's ``agentview`` camera, 256 px) with an
overlay and encodes an mp4 with ffmpeg (``imageio`` + ``imageio-ffmpeg``).

    recorder = VideoRecorder("results/run/videos/detaug_spatial_L2_ep3.mp4", label="detaug")
    rollout(env, policy, seed=3, hooks=[recorder])    # env made with render_mode="rgb_array"
    recorder.save()                                    # or recorder.discard()

Rendering costs ~60 ms a frame on 2 CPU cores, so the bench renders only when asked (``--video N``,
``--video-failures``); an env made without ``render_mode`` never renders.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from detaug_gym.rollout import Hook, Step

FPS = 20  # the control rate: one frame per env step, real time


def _imageio():
    try:
        import imageio.v2 as iio
        import imageio_ffmpeg  # noqa: F401
    except ImportError as exc:  # pragma: no cover - declared dependencies
        raise ImportError("videos need imageio and imageio-ffmpeg: pip install imageio imageio-ffmpeg") from exc
    return iio


class VideoRecorder(Hook):
    """Collects one overlaid frame per step (and the first frame); :meth:`save` writes the mp4.

    Args:
        path: the mp4 to write (parent folders are created on save).
        label: text shown top left with the step counter (e.g. the method).
    """

    def __init__(self, path: str | Path, label: str = "") -> None:
        self.path = Path(path)
        self.label = label
        self.frames: list[np.ndarray] = []
        self.env = None

    def on_start(self, env, obs, info) -> None:
        self.env = env
        self.frames = [self._frame(0, info)]

    def on_step(self, step: Step) -> None:
        self.frames.append(self._frame(step.index + 1, step.info))

    def _frame(self, index: int, info: dict) -> np.ndarray:
        frame = self.env.render()
        if frame is None:
            raise RuntimeError("the env renders nothing: make it with render_mode='rgb_array' to record videos")
        return overlay(np.asarray(frame), f"{self.label}  step {index}",
                       collision=bool(info.get("collision", False)), success=bool(info.get("is_success", False)))

    def save(self) -> Path:
        """Encode the frames as H.264 mp4 at 20 fps; returns the path."""
        iio = _imageio()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        iio.mimwrite(self.path, self.frames, format="FFMPEG", fps=FPS, codec="libx264", macro_block_size=1,
                     quality=7)
        return self.path

    def discard(self) -> None:
        self.frames = []


def overlay(frame: np.ndarray, text: str, collision: bool, success: bool) -> np.ndarray:
    """``frame`` (H, W, 3) uint8 with ``text`` top left and a status line (collision in red, success in
    green) bottom left."""
    from PIL import Image, ImageDraw

    image = Image.fromarray(frame)
    draw = ImageDraw.Draw(image)
    draw.rectangle((0, 0, image.width, 13), fill=(0, 0, 0))
    draw.text((3, 1), text, fill=(255, 255, 255))
    status = ("COLLISION " if collision else "") + ("SUCCESS" if success else "")
    if status:
        colour = (230, 40, 40) if collision else (40, 200, 60)
        draw.rectangle((0, image.height - 13, image.width, image.height), fill=(0, 0, 0))
        draw.text((3, image.height - 12), status.strip(), fill=colour)
    return np.asarray(image)
