"""The eight symmetries of the square on map images, and a prior averaged over them.

:func:`dihedral` turns or mirrors images so that a normal map stays a normal map (its X/Y
vector components move with the pixels); the training data draws one per crop
(prior/train/data.py). :class:`SelfEnsemble` runs a prior on several of the symmetric copies
of its input, turns each output back (:func:`inverse`) and averages them ("self-ensemble",
Timofte, Rothe and Van Gool, CVPR 2016; Lim et al., EDSR, 2017): a network's errors that do
not follow the symmetry average out. It costs one prior run per copy.
"""

from __future__ import annotations

import torch

from .base import Prior, TileProgress

ORDER = (0, 3, 5, 6, 1, 2, 4, 7)
"""The symmetries in the order a self-ensemble of ``n`` takes the first ``n``: the identity,
the half turn, the two quarter turns, then the four mirrors."""
SIZES = (1, 2, 4, 8)
"""How many symmetric copies a self-ensemble may average."""


def dihedral(x: torch.Tensor, op: int, kind: str | None) -> torch.Tensor:
    """One of the eight symmetries of the square (``op`` in 0..7) on images (N, 3, H, W).

    Bit 0 mirrors left-right, bit 1 mirrors top-bottom, bit 2 transposes (after the flips).
    For a normal map (``kind`` "normal"; encoded, tangent X right and Y up) the vector moves
    with the pixels: a left-right mirror negates X, a top-bottom mirror negates Y, and a
    transpose maps (X, Y) to (-Y, -X) (the image's right becomes its old down, its up the old
    left)."""
    if not 0 <= op < 8:
        raise ValueError(f"op must be 0..7, got {op}")
    if op & 1:
        x = x.flip(-1)
    if op & 2:
        x = x.flip(-2)
    if op & 4:
        x = x.transpose(-1, -2)
    if kind != "normal":
        return x
    n = x * 2.0 - 1.0
    nx, ny, nz = n[:, 0:1], n[:, 1:2], n[:, 2:3]
    if op & 1:
        nx = -nx
    if op & 2:
        ny = -ny
    if op & 4:
        nx, ny = -ny, -nx
    return (torch.cat([nx, ny, nz], 1) + 1.0) * 0.5


def inverse(op: int) -> int:
    """The symmetry that undoes ``op``: flips undo themselves; flips then a transpose are
    undone by the transpose then the flips, which is the transpose after the flips with the
    two mirror axes exchanged."""
    if not 0 <= op < 8:
        raise ValueError(f"op must be 0..7, got {op}")
    if not op & 4:
        return op
    return 4 | ((op & 1) << 1) | ((op & 2) >> 1)


class SelfEnsemble(Prior):
    """``inner`` run on the first ``n`` symmetric copies of its input (:data:`ORDER`), each
    output turned back and the ``n`` averaged; ``kind`` says how the copies are made (normal
    maps turn their vectors). Everything else is ``inner``'s: its name, scales, candidates per
    kind (each averaged the same way, or on ``by_kind``'s number of copies for a kind it
    names), precision and back-projection (each copy is back-projected onto its own input, so
    the average is too)."""

    def __init__(
        self, inner: Prior, n: int, kind: str | None = None, by_kind: dict[str, int] | None = None
    ) -> None:
        super().__init__()
        for m in (n, *(by_kind or {}).values()):
            if m not in SIZES:
                raise ValueError(
                    f"a self-ensemble averages {', '.join(map(str, SIZES))} copies, not {m}"
                )
        self.inner, self.n, self.kind, self.by_kind = inner, n, kind, dict(by_kind or {})
        for attr in ("name", "scales", "device", "is_network", "one_pass_scales", "back_project"):
            setattr(self, attr, getattr(inner, attr))

    def _forward(self, x: torch.Tensor, scale: int) -> torch.Tensor:  # pragma: no cover
        raise NotImplementedError("a self-ensemble runs through upscale()")

    def num_parameters(self) -> int:
        return self.inner.num_parameters()

    def _copies(self, kind: str) -> int:
        return self.by_kind.get(kind, self.n)

    def for_kind(self, kind: str) -> Prior:
        inner = self.inner.for_kind(kind)
        n = self._copies(kind)
        return SelfEnsemble(inner, n, kind) if n > 1 else inner

    def candidates(self, kind: str, scale: int) -> list[Prior]:
        n = self._copies(kind)
        inner = self.inner.candidates(kind, scale)
        return [SelfEnsemble(c, n, kind) if n > 1 else c for c in inner]

    def int8_ready(self) -> bool:
        return self.inner.int8_ready()

    def precision_in_use(self) -> str:
        return self.inner.precision_in_use()

    def upscale(
        self,
        images: torch.Tensor,
        scale: int,
        *,
        progress: TileProgress | None = None,
        tile_size: int | None = None,
        tile_overlap: int | None = None,
    ) -> torch.Tensor:
        out = None
        for k, op in enumerate(ORDER[: self.n]):

            def tick(done: int, of: int, k: int = k) -> None:
                if progress is not None:
                    progress(k * of + done, self.n * of)

            copy = dihedral(images, op, self.kind)
            up = self.inner.upscale(copy, scale, progress=tick, tile_size=tile_size,
                                    tile_overlap=tile_overlap)  # fmt: skip
            with torch.inference_mode():
                back = dihedral(up, inverse(op), self.kind)
                out = back.clone() if out is None else out.add_(back)
        assert out is not None
        with torch.inference_mode():
            out = out.div_(self.n).clamp_(0.0, 1.0)
        return out.clone()


def averaged(prior: Prior, n: int, by_kind: dict[str, int] | None = None) -> Prior:
    """``prior`` on ``n`` symmetric copies (:class:`SelfEnsemble`; the map kinds ``by_kind``
    names on its number), or ``prior`` itself where the copies would all come back the same:
    one copy for every kind, or bicubic interpolation, which commutes with every turn and
    mirror."""
    by_kind = {k: m for k, m in (by_kind or {}).items() if m != n}
    if not prior.is_network or (n == 1 and not by_kind):
        return prior
    return SelfEnsemble(prior, n, by_kind=by_kind)
