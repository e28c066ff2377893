"""Conditional flow matching on plan chunks: the training loss and an Euler sampler with hooks.

Convention (used by every caller, CAPE and guidance included): flow time ``t`` runs from **0 = noise** to
**1 = data** along the linear path ``x_t = (1 - t) x0 + t x1`` with ``x0 ~ N(0, I)`` and ``x1`` a normalised
plan; the network regresses the constant velocity ``x1 - x0``. Sampling integrates ``dx/dt = v(x, t)``
from ``t_start`` to 1 with Euler steps, so "re-noise to t0 = 0.92" means *mostly data, a little noise*
and guidance "for t >= chi = 0.8" acts in the last steps.

Inpainting: the known entries (the plan's first state = the current robot state) are held at their clean
value in ``x_t`` both in training and at every sampling step, and excluded from the loss. The network
therefore always sees them clean, which is more accurate than diffusion-style replacement with a noised
copy and costs nothing.

The sampler knows nothing about the network: it takes ``velocity(x, t) -> v`` (a closure that already
holds the observation, label and extra conditioning), which keeps this module reusable by every method.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

VelocityFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
"""``velocity(x (B, H, D), t (B,)) -> (B, H, D)``."""


@dataclass
class Inpaint:
    """Entries of the plan fixed to known values: ``x = where(mask, value, x)``.

    Attributes:
        mask: bool, broadcastable to (B, H, D); True where the value is known.
        value: known (normalised) values, broadcastable to (B, H, D).
    """

    mask: torch.Tensor
    value: torch.Tensor

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        return torch.where(self.mask, self.value.to(x.dtype), x)


@dataclass
class Guidance:
    """Gradient guidance in the late sampling steps: ``x <- x - scale * grad_x cost`` for ``t >= t_min``.

    Attributes:
        cost: ``cost(plan (B, H, D), t) -> (B,)`` per-sample cost of a *normalised* plan (wrap
            unnormalisation inside, as :meth:`detaug_gym.models.policy.FlowPolicy.plan` does).
        scale: lambda, the step size on the gradient.
        t_min: chi, guidance acts at flow times ``t >= t_min`` (late steps, near data).
        on_prediction: evaluate the cost on the predicted clean plan ``x + (1 - t) v`` (the velocity held
            fixed, so the gradient is the cost gradient at the prediction) instead of on the noisy ``x``.
    """

    cost: Callable[[torch.Tensor, float], torch.Tensor]
    scale: float = 3.0
    t_min: float = 0.8
    on_prediction: bool = True

    def step(self, x: torch.Tensor, v: torch.Tensor, t: float) -> torch.Tensor:
        """Return the guidance displacement ``-scale * grad`` for the current state (B, H, D)."""
        with torch.enable_grad():
            point = (x + (1.0 - t) * v).detach() if self.on_prediction else x.detach()
            point.requires_grad_(True)
            cost = self.cost(point, t)
            (grad,) = torch.autograd.grad(cost.sum(), point)
        return -self.scale * grad


def interpolate(x0: torch.Tensor, x1: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """The linear path ``(1 - t) x0 + t x1``; ``t`` (B,) broadcasts over the trailing dims."""
    t = t.view(-1, *([1] * (x1.dim() - 1)))
    return (1.0 - t) * x0 + t * x1


def flow_matching_loss(velocity: VelocityFn, x1: torch.Tensor, inpaint: Inpaint | None = None,
                       generator: torch.Generator | None = None) -> torch.Tensor:
    """Mean squared velocity error on a batch of clean normalised plans ``x1`` (B, H, D).

    ``t`` is uniform on [0, 1]; inpainted entries are clean in ``x_t`` and excluded from the mean. The noise is
    drawn on the CPU (``generator`` is a CPU generator) and moved to ``x1``'s device.
    """
    x0 = torch.randn(x1.shape, generator=generator, dtype=x1.dtype).to(x1.device)
    t = torch.rand(x1.shape[0], generator=generator, dtype=x1.dtype).to(x1.device)
    xt = interpolate(x0, x1, t)
    if inpaint is not None:
        xt = inpaint.apply(xt)
    err = (velocity(xt, t) - (x1 - x0)).pow(2)
    if inpaint is None:
        return err.mean()
    weight = (~inpaint.mask).to(err.dtype).expand_as(err)
    return (err * weight).sum() / weight.sum().clamp_min(1.0)


def euler_times(steps: int, t_start: float = 0.0) -> list[float]:
    """The Euler grid from ``t_start`` to 1: ``steps`` equal intervals (``steps + 1`` points)."""
    if steps < 1 or not 0.0 <= t_start < 1.0:
        raise ValueError(f"need steps >= 1 and 0 <= t_start < 1, got steps={steps}, t_start={t_start}")
    return [t_start + (1.0 - t_start) * k / steps for k in range(steps + 1)]


def remaining_steps(total_steps: int, t_start: float) -> int:
    """Euler steps left when starting at ``t_start`` on a ``total_steps`` schedule (at least 1)."""
    return max(1, round((1.0 - t_start) * total_steps))


def sample(velocity: VelocityFn, shape: tuple[int, ...], *, steps: int = 10, t_start: float = 0.0,
           x_start: torch.Tensor | None = None, inpaint: Inpaint | None = None,
           guidance: Guidance | None = None, generator: torch.Generator | None = None,
           noise: torch.Tensor | None = None, dtype: torch.dtype = torch.float32,
           device: torch.device | str = "cpu") -> torch.Tensor:
    """Integrate the flow from ``t_start`` to 1 and return normalised plans ``shape`` = (B, H, D).

    Args:
        velocity: the conditioned network, ``velocity(x, t)``.
        steps: Euler steps between ``t_start`` and 1 (10 from pure noise; use :func:`remaining_steps` to
            keep the step size of a 10-step schedule when starting later).
        t_start: 0 starts from pure noise. With ``x_start`` (a clean normalised plan, e.g. CAPE's shifted
            unexecuted remainder), the start is the re-noised ``(1 - t_start) noise + t_start x_start``.
        inpaint: known entries held fixed at every step.
        guidance: optional gradient guidance (late steps only).
        generator: source of the initial noise, for reproducible plans: a CPU generator, so a seed gives the
            same noise on every device.
        noise: the initial noise ``shape`` itself (drawn by the caller), instead of drawing it here.
        device: where ``velocity`` runs (``x_start`` and ``inpaint`` must be there too).

    Runs under ``torch.inference_mode`` (``no_grad`` with guidance, whose step needs autograd).
    """
    with torch.no_grad() if guidance is not None else torch.inference_mode():
        if noise is None:
            noise = torch.randn(shape, generator=generator, dtype=dtype)
        return _integrate(velocity, shape, steps, t_start, x_start, inpaint, guidance, noise.to(device), dtype,
                          device)


def _integrate(velocity, shape, steps, t_start, x_start, inpaint, guidance, noise, dtype, device):
    if x_start is not None:
        x = interpolate(noise, x_start.to(dtype).expand(shape),
                        torch.full((shape[0],), t_start, dtype=dtype, device=device))
    elif t_start > 0.0:
        raise ValueError("t_start > 0 needs x_start (the plan to re-noise)")
    else:
        x = noise
    times = euler_times(steps, t_start)
    for t0, t1 in zip(times[:-1], times[1:]):
        if inpaint is not None:
            x = inpaint.apply(x)
        v = velocity(x, torch.full((shape[0],), t0, dtype=dtype, device=device))
        step = (t1 - t0) * v
        if guidance is not None and t0 >= guidance.t_min:
            step = step + guidance.step(x, v, t0)
        x = x + step
    return inpaint.apply(x) if inpaint is not None else x
