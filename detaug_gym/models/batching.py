"""Plan requests and their batched integration: one network call for the plans of several episodes.

A :class:`PlanRequest` is what one :meth:`~detaug_gym.models.policy.FlowPolicy.plan` call integrates: the
normalised conditioning of its K samples, the inpainted first state, the initial noise (already drawn from the
policy's own generator, so batching never changes it), the optional re-noised start, the guidance and the
Euler schedule. :func:`run_requests` concatenates the requests that can share a call (same network, schedule,
start kind and guidance settings) along the batch, integrates each group in one
:func:`~detaug_gym.models.flow.sample` and splits the result. A lone request runs the same code, so the
batched and the unbatched path differ only in the batch size the kernels see.

:class:`PlanBatcher` runs the ``act`` calls of several envs' policies at one env step, each in its own thread
(the threads are the policies' call stacks, not parallelism: they take turns). A policy that replans hands
its request to the batcher and waits; once every ``act`` is waiting or finished, the waiting requests are
integrated together, in slot order, and each goes on with its own plans. Policies
need no batched code path of their own: DetAug scores its K candidates, CAPE its guided remainder, AEGIS
filters the action, each in its own thread as it would alone.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass
from typing import Any

import torch

from detaug_gym.models.flow import Guidance, Inpaint, sample


@dataclass
class PlanRequest:
    """One ``plan`` call's flow integration, every tensor on ``noise``'s device.

    Attributes:
        network: the :class:`~detaug_gym.models.network.FlowNetwork` whose DiT gives the velocity.
        weights: what identifies the network's weights (checkpoint digest and device): requests with the same
            run through one network.
        obs_cond: normalised observation conditioning (K, C).
        label: augmentation labels (K, L), or None (the null token / no label).
        extra: extra conditioning (K, E) (DemoGen's cloud embedding), or None.
        inpaint: the known first state, (K, H, D) mask and value.
        noise: the initial noise (K, H, D).
        x_start: the clean plan to re-noise to ``t_start`` (K, H, D), or None (start from noise).
        t_start: flow time the integration starts at.
        steps: Euler steps.
        guidance: gradient guidance on this request's samples, or None.
    """

    network: Any
    weights: Hashable
    obs_cond: torch.Tensor
    label: torch.Tensor | None
    extra: torch.Tensor | None
    inpaint: Inpaint
    noise: torch.Tensor
    x_start: torch.Tensor | None
    t_start: float
    steps: int
    guidance: Guidance | None = None

    @property
    def size(self) -> int:
        return len(self.noise)

    def group(self) -> tuple:
        """Requests with equal groups share one integration."""
        g = self.guidance
        return (self.weights, self.steps, self.t_start, self.x_start is None, self.label is None,
                self.extra is None, None if g is None else (g.scale, g.t_min, g.on_prediction))


def run_requests(requests: Sequence[PlanRequest]) -> list[torch.Tensor]:
    """The normalised plans (K_i, H, D) of each request, integrating every group of compatible ones at once."""
    out: list[torch.Tensor | None] = [None] * len(requests)
    groups: dict[tuple, list[int]] = {}
    for i, request in enumerate(requests):
        groups.setdefault(request.group(), []).append(i)
    for members in groups.values():
        parts = [requests[i] for i in members]
        plans = _integrate(parts) if len(parts) > 1 else _integrate_one(parts[0])
        for i, plan in zip(members, plans.split([p.size for p in parts])):
            out[i] = plan
    return out


def _integrate_one(r: PlanRequest) -> torch.Tensor:
    return _sample(r.network, r.obs_cond, r.label, r.extra, r.inpaint, r.noise, r.x_start, r.t_start, r.steps,
                   r.guidance)


def _integrate(parts: list[PlanRequest]) -> torch.Tensor:
    first = parts[0]

    def cat(name: str) -> torch.Tensor | None:
        values = [getattr(p, name) for p in parts]
        return None if values[0] is None else torch.cat(values)

    inpaint = Inpaint(torch.cat([p.inpaint.mask.expand_as(p.noise) for p in parts]),
                      torch.cat([p.inpaint.value.expand_as(p.noise) for p in parts]))
    guidance = None
    if first.guidance is not None:
        sizes = [p.size for p in parts]

        def cost(x: torch.Tensor, t: float) -> torch.Tensor:
            return torch.cat([p.guidance.cost(chunk, t) for p, chunk in zip(parts, x.split(sizes))])

        guidance = Guidance(cost, first.guidance.scale, first.guidance.t_min, first.guidance.on_prediction)
    return _sample(first.network, cat("obs_cond"), cat("label"), cat("extra"), inpaint, cat("noise"),
                   cat("x_start"), first.t_start, first.steps, guidance)


def _sample(network, obs_cond, label, extra, inpaint, noise, x_start, t_start, steps, guidance) -> torch.Tensor:
    def velocity(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return network.dit(x, t, obs_cond, label, extra)

    return sample(velocity, tuple(noise.shape), steps=steps, t_start=t_start, x_start=x_start, inpaint=inpaint,
                  guidance=guidance, noise=noise, dtype=noise.dtype, device=noise.device)


class PlanBatcher:
    """Integrates the plan requests of several policies' ``act`` calls at one env step together (module
    docstring).

    The ``act`` calls take turns, in slot order: one runs until it asks for a plan (or returns), then the next;
    when none can run, the waiting requests are integrated together and their callers go on, again one at a
    time in slot order. So no two policies ever run at once (no library they call needs to be thread-safe) and
    the order of everything is fixed, whatever the OS does with the threads.

    Attributes:
        requests: plan requests served so far; integrations: network integrations they took.
    """

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._local = threading.local()
        self._pending: list[tuple[int, PlanRequest]] = []  # (slot, request)
        self._done: dict[int, torch.Tensor | BaseException] = {}  # slot -> its plans
        self._state: list[str] = []  # per slot: ready | waiting | done
        self._turn: int | None = None
        self.requests = self.integrations = 0

    def run_all(self, calls: Sequence[Callable[[], Any]]) -> list[Any]:
        """Run ``calls`` (one per slot), taking turns as above; returns each one's result, or the exception it
        raised (one slot's failure does not stop the others)."""
        results: list[Any] = [None] * len(calls)
        with self._cond:
            self._state, self._turn = ["ready"] * len(calls), 0 if calls else None

        def work(slot: int) -> None:
            self._local.slot = slot
            with self._cond:
                self._cond.wait_for(lambda: self._turn == slot)
            try:
                results[slot] = calls[slot]()
            except BaseException as exc:  # noqa: BLE001  (handed back to the caller)
                results[slot] = exc
            finally:
                with self._cond:
                    self._state[slot] = "done"
                    self._next_turn()

        threads = [threading.Thread(target=work, args=(slot,), daemon=True) for slot in range(len(calls))]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        self._local.slot = None
        return results

    def submit(self, request: PlanRequest) -> torch.Tensor:
        """The request's plans, integrated with the other slots' once none of them can run on. Outside
        :meth:`run_all` (no slot) the request runs at once."""
        slot = getattr(self._local, "slot", None)
        if slot is None:
            return run_requests([request])[0]
        with self._cond:
            self._pending.append((slot, request))
            self._state[slot] = "waiting"
            self._next_turn()
            self._cond.wait_for(lambda: self._turn == slot)
            result = self._done.pop(slot)
        if isinstance(result, BaseException):
            raise result
        return result

    def _next_turn(self) -> None:
        """With the lock held, once the running slot stopped: the next ready slot runs; with none, the pending
        requests are integrated and their slots run on."""
        ready = [s for s, state in enumerate(self._state) if state == "ready"]
        if not ready and self._pending:
            pending, self._pending = sorted(self._pending, key=lambda p: p[0]), []
            try:
                plans = run_requests([request for _, request in pending])
            except BaseException as exc:  # noqa: BLE001  (every waiting policy gets it)
                plans = [exc] * len(pending)
            self.requests += len(pending)
            self.integrations += len({request.group() for _, request in pending})
            for (slot, _), plan in zip(pending, plans):
                self._done[slot] = plan
                self._state[slot] = "ready"
            ready = [slot for slot, _ in pending]
        self._turn = ready[0] if ready else None
        self._cond.notify_all()
