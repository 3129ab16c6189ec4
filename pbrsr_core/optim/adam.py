"""Adam (Kingma and Ba 2015) through torch's fused kernel, without ``torch.optim``.

``torch.optim.Optimizer``'s constructor imports ``torch._dynamo`` (through
``torch._disable_dynamo``): 2.7 s of a 13 s fast-preset run on this project's 2-core AMD CPU,
paid by every CLI call and every benchmark subprocess. The update itself is the same kernel
``torch.optim.Adam(fused=True)`` calls, ``aten::_fused_adam_`` (one pass over a parameter, its
gradient and its two moments; CPU and CUDA), with torch's defaults: betas (0.9, 0.999),
eps 1e-8, no weight decay, bias-corrected with a per-parameter step count.
tests/core/optim/test_adam.py compares it with ``torch.optim.Adam`` step for step.
"""

from __future__ import annotations

import torch


class FusedAdam:
    """Adam over groups of tensors, each group with its own learning rate.

    ``groups``: ``[(lr, [tensor, ...]), ...]``; every tensor is a leaf whose ``.grad`` the
    caller fills. A tensor without a gradient at a step is skipped (its moments and step
    count stay), as ``torch.optim.Adam`` does."""

    def __init__(
        self,
        groups: list[tuple[float, list[torch.Tensor]]],
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
    ) -> None:
        for lr, params in groups:
            if not lr > 0.0:
                raise ValueError(f"Adam learning rate must be > 0, got {lr}")
            if any(not p.is_floating_point() for p in params):
                raise TypeError("Adam parameters must be floating-point tensors")
        self.groups = [(float(lr), list(params)) for lr, params in groups]
        self.betas = (float(betas[0]), float(betas[1]))
        self.eps = float(eps)
        self._state: dict[int, tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = {}

    @property
    def lrs(self) -> list[float]:
        """The groups' learning rates, in order."""
        return [lr for lr, _ in self.groups]

    def _moments(self, p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        state = self._state.get(id(p))
        if state is None:
            state = (
                torch.zeros_like(p, memory_format=torch.preserve_format),
                torch.zeros_like(p, memory_format=torch.preserve_format),
                torch.zeros((), dtype=torch.float32, device=p.device),  # step count
            )
            self._state[id(p)] = state
        return state

    @torch.no_grad()
    def step(self) -> None:
        for lr, params in self.groups:
            # (parameters, their gradients) per device and dtype
            by_kind: dict[tuple, tuple[list[torch.Tensor], list[torch.Tensor]]] = {}
            for p in params:
                if p.grad is not None:
                    ps, gs = by_kind.setdefault((p.device, p.dtype), ([], []))
                    ps.append(p)
                    gs.append(p.grad)
            for ps, gs in by_kind.values():  # the kernel takes one device and dtype per call
                state = [self._moments(p) for p in ps]
                steps = [s[2] for s in state]
                torch._foreach_add_(steps, 1)
                torch._fused_adam_(
                    ps,
                    gs,
                    [s[0] for s in state],
                    [s[1] for s in state],
                    [],
                    steps,
                    lr=lr,
                    beta1=self.betas[0],
                    beta2=self.betas[1],
                    weight_decay=0.0,
                    eps=self.eps,
                    amsgrad=False,
                    maximize=False,
                )
