"""The optimiser's schedule: the learning rate of every channel, which views each iteration
renders, which iterations are logged, and the snapshots a caller asked for."""

from __future__ import annotations

from collections.abc import Callable, Collection

import torch

from .losses import MapGroup
from .presets import PbrsrConfig


def channel_lr(groups: list[MapGroup], channels: int, config: PbrsrConfig) -> torch.Tensor:
    """(C,) Adam learning rates of one image's channels: ``config.lr`` times the map's factor
    in ``config.map_lr``; channels no group owns get 0 (they keep their init)."""
    out = torch.zeros(channels, dtype=torch.float64)  # exact config values for Adam
    for g in groups:
        out[list(g.channels)] = config.lr * config.map_lr.get(g.name, 1.0)
    return out


class ViewBatches:
    """``batch`` views per iteration (``sampling="views"``): the views in a random order, a
    new permutation (from ``gen``) appended whenever fewer than a batch remain."""

    def __init__(self, n_views: int, batch: int, gen: torch.Generator):
        self.n_views, self.batch, self.gen = n_views, batch, gen
        self.order: list[int] = []

    def next(self) -> list[int]:
        while len(self.order) < self.batch:
            self.order.extend(torch.randperm(self.n_views, generator=self.gen).tolist())
        batch, self.order = self.order[: self.batch], self.order[self.batch :]
        return batch


def logged(done: int, config: PbrsrConfig) -> bool:
    """Whether the iteration that completes step ``done`` (1-based) is logged and reported:
    every ``log_every``, the first and the last."""
    return done % config.log_every == 0 or done == config.iterations or done == 1


class Snapshots:
    """Calls ``on_snapshot(it, maps())`` before each iteration in ``at`` (and after the last,
    ``it == iterations``)."""

    def __init__(
        self,
        at: Collection[int],
        on_snapshot: Callable[[int, dict[int, torch.Tensor]], None] | None,
        maps: Callable[[], dict[int, torch.Tensor]],
    ):
        self.at, self.on_snapshot, self.maps = at, on_snapshot, maps

    def __call__(self, it: int) -> None:
        if self.on_snapshot is not None and it in self.at:
            self.on_snapshot(it, self.maps())
