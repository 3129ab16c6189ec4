"""FusedAdam against torch.optim.Adam, the reference it replaces."""

import subprocess
import sys

import pytest
import torch

from pbrsr_core.optim.adam import FusedAdam


def _pair(shapes, seed):
    gen = torch.Generator().manual_seed(seed)
    init = [torch.rand(s, generator=gen) for s in shapes]
    return [t.clone().requires_grad_() for t in init], [t.clone().requires_grad_() for t in init]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_matches_torch_adam_over_groups_and_skipped_grads(dtype):
    shapes = [(7, 5, 3), (16,), (4, 4, 1)]
    mine, ref = _pair(shapes, 0)
    mine = [t.detach().to(dtype).requires_grad_() for t in mine]
    ref = [t.detach().to(dtype).requires_grad_() for t in ref]
    opt = FusedAdam([(3e-2, mine[:2]), (1e-3, mine[2:])], eps=1e-6)
    ref_opt = torch.optim.Adam(
        [{"params": ref[:2], "lr": 3e-2}, {"params": ref[2:], "lr": 1e-3}], eps=1e-6
    )
    gen = torch.Generator().manual_seed(1)
    for step in range(12):
        for k, (a, b) in enumerate(zip(mine, ref, strict=True)):
            if k == 1 and step % 3 == 1:  # no gradient this step: skipped, state kept
                a.grad = b.grad = None
                continue
            g = (torch.randn(a.shape, generator=gen) * 10.0 ** -(step % 5)).to(dtype)
            a.grad, b.grad = g.clone(), g.clone()
        opt.step()
        ref_opt.step()
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    for a, b in zip(mine, ref, strict=True):
        assert torch.allclose(a.detach(), b.detach(), atol=tol, rtol=0)


def test_first_step_moves_by_lr_times_sign():
    p = torch.zeros(5, requires_grad=True)
    p.grad = torch.tensor([2.0, -3.0, 1e-3, -1e-3, 0.5])
    FusedAdam([(0.1, [p])]).step()
    assert torch.allclose(p.detach(), -0.1 * torch.sign(p.grad), atol=1e-6)


def test_bad_arguments_refused():
    with pytest.raises(ValueError, match="learning rate"):
        FusedAdam([(0.0, [torch.zeros(2, requires_grad=True)])])
    with pytest.raises(TypeError, match="floating-point"):
        FusedAdam([(1e-3, [torch.zeros(2, dtype=torch.long)])])


def test_optimiser_run_does_not_import_dynamo():
    """The reason FusedAdam exists: torch.optim's constructor imports torch._dynamo (seconds
    per process). A short PBR-SR optimisation in a fresh interpreter must not."""
    code = (
        "import sys, torch\n"
        "from pbrsr_core.optim.adam import FusedAdam\n"
        "from pbrsr_core.optim.whole_map import MapAdam\n"
        "p = torch.rand(8, 8, 3, requires_grad=True); w = torch.ones(2, 4, 4, requires_grad=True)\n"
        "rate, owned = torch.full((3,), 1e-3), torch.ones(3, dtype=torch.bool)\n"
        "m = MapAdam({0: p}, {0: rate}, {0: False}, {0: owned})\n"
        "a = FusedAdam([(1e-3, [w])])\n"
        "p.grad = torch.randn(8, 8, 3); w.grad = torch.randn(2, 4, 4)\n"
        "m.step(); a.step()\n"
        "print('torch._dynamo' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
