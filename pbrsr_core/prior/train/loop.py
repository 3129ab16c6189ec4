"""The training loop of a texture prior: AdamW with the learning rate halved at 40 % and 80 %
of the steps, L1 on the HR crop's interior (of the output as it is, or back-projected onto the
LR crop as the prior runs it: :data:`LOSSES`), EMA weights, validation on held-out crops,
checkpoints a run resumes from exactly, and the best EMA weights by validation written as
safetensors (:mod:`pbrsr_core.prior.texture` loads them).

The network is an :class:`~pbrsr_core.prior.waifu2x.UpConv7`, a
:class:`~pbrsr_core.prior.compact.Compact`, a :class:`~pbrsr_core.prior.span.Span` or a
:class:`~pbrsr_core.prior.srmd.SRMD` network, or any SR model spandrel loads
(:class:`~pbrsr_core.prior.spandrel_prior.SpandrelNet`, fine-tuned from its weights file), of
stride 2 or 4 (x4 training of a stride-2 network chains two passes with a clamp between them,
as inference does). A run with ``first``
trains a later-pass network: the frozen ``first`` network makes the first x2 pass, the trained
one the second; the run's folder gets a copy of the first network beside the trained one, so
the folder is a texture set of its own."""

from __future__ import annotations

import copy
import json
import math
import os
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch

from ...degrade import check_kernels
from ...errors import InvalidOptions, PriorUnavailable
from .. import compact, srmd
from ..backproject import back_project
from ..int8 import Calibration, FakeInt8, Int8SRMD, calibrate
from ..waifu2x import UpConv7
from . import weights
from .data import KINDS, CropSampler, Material, degrade_pair, validation_crops

CHECKPOINT = "checkpoint.pt"
LOSSES = ("l1", "l1-backprojected")
"""``l1``: L1 between the network's output and the HR crop. ``l1-backprojected``: L1 between
the output after one back-projection step onto the LR crop (prior/backproject.py, as every
network prior runs at inference and as validation scores it) and the HR crop, so that the
network is not taught what that step puts right by itself (low-frequency offsets). On pbr-srmd's
colour network it scored no better than ``l1`` (docs/BENCHMARKS.md, "The loss compared after
back-projection"), which stays the default."""
HISTORY = "history.json"


@dataclass
class TrainConfig:
    """Everything a run depends on; stored in its checkpoint and its weights' metadata."""

    kinds: tuple[str, ...] = KINDS
    """Map kinds this network learns: one (a network per kind) or several (one shared)."""
    scale: int = 2
    steps: int = 3000
    loss: str = "l1"
    """One of :data:`LOSSES`; a distilling run (``distill``) has a loss of its own."""
    batch_size: int = 8
    patch: int = 96
    """HR crop side in pixels."""
    lr: float = 5e-5
    weight_decay: float = 1e-5
    ema: float = 0.999
    seed: int = 0
    arch: str = "upconv7"
    """``upconv7``, ``compact``, ``span`` or ``srmd``
    (:func:`~pbrsr_core.prior.train.weights.new_network`), or ``spandrel`` (``init``
    ``spandrel:<file>``: the file's architecture and scale, no widths)."""
    widths: tuple[int, ...] = (16, 32, 64, 128, 128, 256)
    stride: int = 2
    """Upscaling of one network pass: 2 (``scale`` 4 chains two passes), 4 or 8 (SRMD)."""
    residual: bool = False
    """UpConv7 only: the network's output is added to a bicubic resize of its input (at
    random start weights: bicubic exactly)."""
    first: str | None = None
    """Weights file of a frozen x2 network that makes the first pass; this run's network
    (stride 2, ``scale`` 4) learns the pass after it. None: the network makes every pass."""
    distill: bool = False
    """With ``first``: the target is the ``first`` network's own second pass (its output on
    its first pass's output, clamped), not the HR crop, so a narrow later network learns to do
    what the wide one does at x4, edges of drawn textures included, which the HR crops of
    natural materials seldom show. Validation then scores agreement with that second pass on
    the held-out crops (the HR crops hardly tell later passes apart). Without ``first``: the
    target is the start weights' own output at the run's scale (clamped), so a network pruned
    narrower (``widths``) learns what the full one does; the loss compares both outputs
    back-projected onto the LR crop, as the prior runs them (a pruned network's error is
    mostly of low frequency, which that step removes: on raw outputs its detail got worse
    while that error was learnt away); validation scores the HR crops."""
    init: str = "waifu2x-photo"
    """Start weights: ``waifu2x-photo`` (UpConv7), ``realesr-animevideov3`` (compact), ``srmdnf``
    (SRMD, of the run's stride), a weights file, ``spandrel:<file>`` (any SR model spandrel
    recognises, of the run's stride), or ``random`` (seeded). Start weights of
    another stride give the convolutions; the new head starts at random, except that an SRMD
    head of half the run's stride starts as its own output enlarged x2 by nearest neighbour."""
    jpeg: tuple[int, int] | None = None
    """JPEG stage of the LR model: a quality range (inclusive) for ``jpeg_share`` of the LR
    crops (:func:`~pbrsr_core.prior.train.data.jpeg_lr`); None: the protocol's blur + bicubic
    only."""
    jpeg_share: float = 0.5
    kernels: tuple[str, ...] = ("gaussian",)
    """Downsampling kernels of the LR crops (:data:`~pbrsr_core.degrade.KERNELS`), one drawn
    per crop; validation takes them in turn over its crops. The protocol's Gaussian alone
    trains for inputs made as the benchmark makes them; a mix, for LR maps made otherwise
    (mipmaps, image editors)."""
    graphics: float = 0.0
    """Share of the crops drawn procedurally (text, shapes, lines in colour, in grey levels as
    a data map, or raised and sunk as a normal map: :mod:`~pbrsr_core.prior.train.graphics`)
    instead of cut from a material; a drawing is its own HR ground truth, and with ``distill``
    the target is the first network's second pass."""
    int8: bool = False
    """SRMD only: train through the int8 network's rounding (:class:`~pbrsr_core.prior.int8.
    FakeInt8`, activation ranges calibrated on the start weights), and validate it in int8,
    so that the network loses less when it runs in int8."""
    val_every: int = 250
    val_patch: int = 128
    ckpt_every: int = 250
    threads: int = 0
    """torch threads (0: torch's default)."""

    def check(self) -> None:
        for k in self.kinds:
            if k not in KINDS:
                raise InvalidOptions(f"unknown map kind {k!r}: use {', '.join(KINDS)}")
        if self.scale not in (2, 4, 8):
            raise InvalidOptions(f"training scale must be 2, 4 or 8, not {self.scale}")
        powers = {self.stride**k for k in (1, 2, 3)}  # the scale is whole passes of the stride
        if self.stride not in (2, 4, 8) or self.scale not in powers:
            raise InvalidOptions(
                f"a network of stride {self.stride} cannot be trained at x{self.scale}"
            )
        if self.loss not in LOSSES:
            raise InvalidOptions(f"unknown loss {self.loss!r}: use {', '.join(LOSSES)}")
        if self.distill and self.loss != "l1":
            raise InvalidOptions(
                "--loss is for runs against the HR crop; a distilling run compares with its "
                "teacher's output"
            )
        if self.steps < 1 or self.batch_size < 1:
            raise InvalidOptions("steps and batch size must be at least 1")
        if self.patch % self.scale or self.val_patch % self.scale:
            raise InvalidOptions("patch sizes must be multiples of the scale")
        if self.patch <= 8 * self.scale:
            raise InvalidOptions(
                f"the patch must be larger than {8 * self.scale} px at x{self.scale} (the loss "
                f"leaves out {4 * self.scale} px at each border)"
            )
        if self.jpeg is not None and not 1 <= self.jpeg[0] <= self.jpeg[1] <= 100:
            raise InvalidOptions(f"JPEG qualities must be LOW-HIGH within 1..100, not {self.jpeg}")
        if not 0.0 < self.jpeg_share <= 1.0:
            raise InvalidOptions(f"the JPEG share must be in (0, 1], not {self.jpeg_share}")
        check_kernels(self.kernels)
        if not 0.0 <= self.graphics <= 1.0:
            raise InvalidOptions(f"the graphics share must be in [0, 1], not {self.graphics}")
        if not (0.0 <= self.ema < 1.0):
            raise InvalidOptions(f"ema must be in [0, 1), not {self.ema}")
        if self.arch == "spandrel" or self.init.startswith(weights.SPANDREL):
            self._check_spandrel()
        else:
            try:
                weights.new_network(self.arch, self.widths, self.stride, self.residual)
            except ValueError as exc:
                raise InvalidOptions(str(exc)) from exc
        if self.int8 and (self.arch != "srmd" or self.first is not None):
            raise InvalidOptions("--int8 trains an SRMD network that makes every pass itself")
        if self.first is not None:
            if self.scale != 4 or self.stride != 2:
                raise InvalidOptions(
                    "a network behind a first pass is trained at scale 4 with stride 2, not "
                    f"scale {self.scale}, stride {self.stride}"
                )
            if first_network(self).stride != 2:
                raise InvalidOptions(f"the first-pass network '{self.first}' is not an x2 network")
        elif self.distill:
            if self.init == "random":
                raise InvalidOptions(
                    "distilling needs a network to learn from: start weights (--from) or a "
                    "first-pass network (--first)"
                )
            if teacher_network(self).stride != self.stride:
                raise InvalidOptions(
                    f"the start weights '{self.init}' are not a stride-{self.stride} network to "
                    "distil"
                )

    def _check_spandrel(self) -> None:
        """A spandrel model is fine-tuned as its file has it: the file's scale is the stride."""
        if self.arch != "spandrel" or not self.init.startswith(weights.SPANDREL):
            raise InvalidOptions(
                "a spandrel network is fine-tuned from its weights: --from spandrel:<file>"
            )
        if self.widths or self.residual or self.int8 or self.first is not None:
            raise InvalidOptions(
                "a spandrel network trains as its file has it: no --widths, --residual, --int8 "
                "or --first"
            )
        net = start_network(self.init, self.stride)
        if net.stride != self.stride:
            raise InvalidOptions(
                f"'{self.init[len(weights.SPANDREL) :]}' is an x{net.stride} "
                f"{net.architecture} model: train it with --stride {net.stride} and a --scale "
                f"it divides"
            )


@dataclass
class History:
    steps: list[int] = field(default_factory=list)
    loss: list[float] = field(default_factory=list)
    val_steps: list[int] = field(default_factory=list)
    val_psnr: dict[str, list[float]] = field(default_factory=dict)
    val_bicubic: dict[str, float] = field(default_factory=dict)
    best_step: int = -1
    best_psnr: float = -math.inf
    seconds: float = 0.0


Progress = Callable[[int, int, dict], None]
"""``progress(step, total, info)`` after each step; ``info`` has ``loss`` and, after a
validation, ``val`` (mean PSNR)."""


def start_network(init: str, stride: int = 2) -> weights.Network:
    """The start weights ``init`` names (not ``random``) as a network; SRMD's of ``stride``
    (its package has a network per scale); ``spandrel:<file>`` the model in the file."""
    if init.startswith(weights.SPANDREL):
        from ..spandrel_prior import SpandrelNet

        return SpandrelNet.from_file(Path(init[len(weights.SPANDREL) :]).expanduser())
    if init == "waifu2x-photo":
        from ..ncnn import read_model
        from ..waifu2x import INSTALL_HINT, model_files

        files = model_files()
        if files is None:
            raise InvalidOptions(f"waifu2x-photo is not installed: {INSTALL_HINT}")
        return UpConv7.from_ncnn(read_model(*files))
    if init == compact.START:
        return compact.start_network()
    if init == srmd.START:
        return srmd.start_network(stride)
    return weights.load_network(Path(init))


def first_network(config: TrainConfig) -> weights.Network:
    """The frozen first-pass network of a later-pass run."""
    assert config.first is not None
    try:
        net = weights.load_network(Path(config.first))
    except PriorUnavailable as exc:
        raise InvalidOptions(f"first-pass network: {exc}") from exc
    return net.eval().requires_grad_(False)


def teacher_network(config: TrainConfig) -> weights.Network:
    """The frozen network whose output a distilling run learns: the first-pass network (its
    second pass) or, without one, the start weights as they are (before any pruning)."""
    if config.first is not None:
        return first_network(config)
    return start_network(config.init, config.stride).eval().requires_grad_(False)


INT8_CALIBRATION_CROPS = 128
"""Training crops an int8 calibration measures its activation ranges on."""


def calibration_crops(
    materials: list[Material], kinds: tuple[str, ...], scale: int, patch: int, n: int, seed: int
) -> torch.Tensor:
    """``n`` LR crops (HR side ``patch``) of ``materials`` for an int8 calibration: drawn as a
    training run draws its batches, the kinds in turn, half of the crops drawn
    procedurally (their hard edges set the activation ranges as much as the materials
    do: pbr-srmd's colour network calibrated on 128² crops of the materials alone scored
    38.42 dB on the shared assets' albedo crops, with half of them drawn 38.60)."""
    sampler = CropSampler(materials, kinds, scale, patch, 8, seed, None, 0.5, 0.5)
    return torch.cat([sampler.batch(i)[0] for i in range(-(-n // 8))])[:n]


CALIBRATION_CROPS = 32
"""LR crops that refit a pruned network's convolutions (:func:`srmd.pruned`): pruning
pbr-srmd's colour network to 112 features at a 128² HR patch raised the peak RSS by 0.4 GB."""


def build_network(config: TrainConfig, materials: list[Material] | None = None) -> weights.Network:
    """The network at its start weights; an SRMD start asked for narrower widths is pruned to
    them, its convolutions refit on LR crops of ``materials`` where given (drawn as the run
    draws its batches, with another seed)."""
    torch.manual_seed(config.seed)
    if config.arch == "spandrel":  # the file's model as it is (TrainConfig.check)
        return start_network(config.init, config.stride)
    net = weights.new_network(config.arch, config.widths, config.stride, config.residual)
    if config.init == "random":
        return net
    start = start_network(config.init, config.stride)
    if (
        isinstance(start, srmd.SRMD)
        and config.arch == "srmd"
        and len(config.widths) == start.convs
        and config.widths[0] < start.feat
    ):
        calibration = None
        if materials:
            sampler = CropSampler(
                materials,
                config.kinds,
                config.scale,
                config.patch,
                config.batch_size,
                config.seed + 1,
                config.jpeg,
                config.jpeg_share,
                config.graphics,
                config.kernels,
            )
            batches = -(-CALIBRATION_CROPS // config.batch_size)
            calibration = torch.cat([sampler.batch(i)[0] for i in range(batches)])
            calibration = calibration[:CALIBRATION_CROPS]
        start = srmd.pruned(start, config.widths[0], calibration)
    residual = getattr(start, "residual", False)  # compact networks have no bicubic branch
    if (
        weights.arch_of(start) != config.arch
        or start.widths != tuple(config.widths)
        or residual != config.residual
    ):
        raise InvalidOptions(
            f"the start weights are {weights.arch_of(start)} of widths {start.widths}"
            f"{' (residual)' if residual else ''}, the config asks for {config.arch} of widths "
            f"{config.widths}{' (residual)' if config.residual else ''}"
        )
    state = start.state_dict()
    if start.stride != config.stride:  # the convolutions only; the head stays as built
        head = weights.head_prefix(start)
        state = {k: v for k, v in state.items() if not k.startswith(head)}
        if isinstance(start, srmd.SRMD) and config.stride == 2 * start.stride:
            state.update({f"{head}{k}": v for k, v in srmd.nearest_head(start.head).items()})
    net.load_state_dict(state, strict=False)
    return net


Runnable = weights.Network | FakeInt8 | Int8SRMD
"""A network as training and validation run it: float, through int8 rounding, or in int8."""


def upscale_net(
    net: Runnable, lr: torch.Tensor, scale: int, first: weights.Network | None = None
) -> torch.Tensor:
    """Passes of ``net`` up to ``scale`` (after one pass of the frozen ``first`` network where
    given), clamped between passes as inference does."""
    x, done = lr, 1
    if first is not None:
        with torch.no_grad():
            x, done = first(lr), first.stride
    while done < scale:
        if done > 1:
            x = x.clamp(0.0, 1.0)
        x = net(x)
        done *= net.stride
    return x


def interior_l1(y: torch.Tensor, hr: torch.Tensor, shave: int) -> torch.Tensor:
    if shave:
        y, hr = y[..., shave:-shave, shave:-shave], hr[..., shave:-shave, shave:-shave]
    return (y - hr).abs().mean()


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float(((a - b) ** 2).mean())
    return 10.0 * math.log10(1.0 / max(mse, 1e-12))


def _in_fours(fn: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor) -> torch.Tensor:
    """``fn`` over ``x`` four images at a time (bounded memory), concatenated."""
    return torch.cat([fn(x[i : i + 4]) for i in range(0, len(x), 4)])


class Validator:
    """PSNR of a network (back-projected, as :class:`~pbrsr_core.prior.base.Prior` runs it)
    on fixed held-out crops, per kind, ``scale`` pixels shaved off each border.

    With ``first`` (a later-pass run's frozen network) the network runs behind one pass of it.
    With ``distill`` too, the network is scored as what it learns: its pass on ``first``'s
    output against ``first``'s own second pass; "bicubic" is then a bicubic second pass. With
    several ``kernels``, crop i's LR is made by kernel i modulo their number, so the score
    weighs each alike. The crops are kept on ``device``, the networks'."""

    def __init__(
        self,
        materials: list[Material],
        kinds,
        scale: int,
        patch: int,
        first: weights.Network | None = None,
        distill: bool = False,
        device: torch.device | str = "cpu",
        kernels: tuple[str, ...] = ("gaussian",),
    ) -> None:
        self.scale, self.sets, self.first = scale, {}, first
        self.teacher = teacher = first if distill else None
        for kind in kinds:
            crops = validation_crops(materials, kind, patch)
            if not crops:
                continue
            hr = torch.stack([torch.from_numpy(c).permute(2, 0, 1).float() / 255 for _, c in crops])
            lr = torch.cat(
                [degrade_pair(hr[i : i + 1], scale, kind, kernels[i % len(kernels)])
                 for i in range(len(hr))]
            ).to(device)  # fmt: skip
            hr = hr.to(device)
            if teacher is not None:  # its first pass, and its second pass on that
                with torch.no_grad():
                    lr = _in_fours(lambda t: teacher(t).clamp(0, 1), lr)
                    hr = _in_fours(lambda t: teacher(t).clamp(0, 1), lr)
            self.sets[kind] = (lr, hr)

    def _score(self, up: torch.Tensor, hr: torch.Tensor) -> float:
        s = self.scale
        return psnr(up[..., s:-s, s:-s], hr[..., s:-s, s:-s])

    def bicubic(self) -> dict[str, float]:
        from ..bicubic import bicubic_upscale

        factor = 2 if self.teacher is not None else self.scale
        return {
            k: self._score(bicubic_upscale(lr, factor).clamp(0, 1), hr)
            for k, (lr, hr) in self.sets.items()
        }

    @torch.no_grad()
    def __call__(self, net: Runnable) -> dict[str, float]:
        out = {}
        for kind, (lr, hr) in self.sets.items():
            if self.teacher is not None:
                up = _in_fours(lambda t: net(t).clamp(0, 1), lr)
            else:
                up = _in_fours(
                    lambda t: upscale_net(net, t, self.scale, self.first).clamp(0, 1), lr
                )
                up = back_project(up, lr, self.scale)
            out[kind] = self._score(up, hr)
        return out


def _milestones(steps: int) -> tuple[int, int]:
    return int(steps * 0.4), int(steps * 0.8)


def _lr_at(config: TrainConfig, step: int) -> float:
    a, b = _milestones(config.steps)
    return config.lr * (0.5 if step >= a else 1.0) * (0.5 if step >= b else 1.0)


def _save_atomic(obj, path: Path) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def train(
    config: TrainConfig,
    train_materials: list[Material],
    val_materials: list[Material],
    out_dir: Path,
    *,
    name: str,
    resume: bool = True,
    progress: Progress | None = None,
    metadata: dict[str, str] | None = None,
    device: torch.device | str = "cpu",
) -> tuple[Path, History]:
    """Train (or resume) one network; returns the best weights file and the history.

    ``out_dir`` receives ``checkpoint.pt`` (every ``ckpt_every`` steps and at the end),
    ``history.json`` and ``<name>.safetensors`` (the best EMA weights by mean validation
    PSNR); a run with ``first`` also ``<name>-first.safetensors``, a copy of the first-pass
    network. A run with ``resume`` picks up its checkpoint and draws the same batches it would
    have drawn without the interruption. The networks train on ``device``; a checkpoint is
    read onto the CPU and copied into them wherever they are."""
    config.check()
    out_dir.mkdir(parents=True, exist_ok=True)
    if config.threads:
        torch.set_num_threads(config.threads)
    first = None
    meta = {**(metadata or {}), "name": name}
    if config.first is not None:
        first = first_network(config).to(device)
        first_file = out_dir / f"{name}-first.safetensors"
        if Path(config.first).resolve() != first_file.resolve():
            shutil.copyfile(config.first, first_file)
        meta["first_sha256"] = weights.file_sha256(first_file)
    # a later-pass run distils its first network's second pass (below); any other, its start
    teacher = teacher_network(config).to(device) if config.distill and first is None else None
    history, start = History(), 0
    ckpt = out_dir / CHECKPOINT
    resuming = resume and ckpt.is_file()
    # resuming, the checkpoint holds the weights: no refit of a pruned start
    net = build_network(config, None if resuming else train_materials).to(device).train()
    ema = copy.deepcopy(net).eval().requires_grad_(False)
    opt = torch.optim.AdamW(
        net.parameters(), lr=config.lr, betas=(0.9, 0.99), weight_decay=config.weight_decay
    )
    sampler = CropSampler(
        train_materials,
        config.kinds,
        config.scale,
        config.patch,
        config.batch_size,
        config.seed,
        config.jpeg,
        config.jpeg_share,
        config.graphics,
        config.kernels,
    )
    validator = Validator(
        val_materials,
        config.kinds,
        config.scale,
        config.val_patch,
        first,
        config.distill,
        device,
        config.kernels,
    )
    best_file = out_dir / f"{name}.safetensors"
    state: dict = {}
    if resuming:
        state = torch.load(ckpt, map_location="cpu", weights_only=False)
        if state["config"] != asdict(config):
            raise InvalidOptions(
                f"{ckpt} was written by a run with other settings; use a new output folder "
                "or --no-resume"
            )
        net.load_state_dict(state["net"])
        ema.load_state_dict(state["ema"])
        opt.load_state_dict(state["opt"])
        history = History(**state["history"])
        start = state["step"]
    student: Runnable = net
    calibration = None
    if config.int8:  # ranges of the start weights; resuming, the checkpoint's
        assert isinstance(net, srmd.SRMD)  # TrainConfig.check
        if resuming:
            calibration = Calibration.from_json(state["int8"], net.convs)
        else:
            crops = calibration_crops(train_materials, config.kinds, config.scale, config.patch,
                                      INT8_CALIBRATION_CROPS, config.seed + 1)  # fmt: skip
            calibration = calibrate(net, crops.to(device))
        student = FakeInt8(net, calibration)
    if not history.val_bicubic:
        history.val_bicubic = validator.bicubic()
    shave = 4 * config.scale  # TrainConfig.check keeps the patch larger than 2 * shave
    t0 = time.perf_counter() - history.seconds
    run_loss, run_n = 0.0, 0
    for step in range(start, config.steps):
        for group in opt.param_groups:
            group["lr"] = _lr_at(config, step)
        lr_img, hr_img, _ = sampler.batch(step)
        lr_img, hr_img = lr_img.to(device), hr_img.to(device)
        if first is not None and config.distill:
            with torch.no_grad():
                mid = first(lr_img).clamp(0.0, 1.0)
                hr_img = first(mid).clamp(0.0, 1.0)
            loss = interior_l1(student(mid), hr_img, shave)
        elif teacher is not None:  # both back-projected, as the prior runs them
            with torch.no_grad():
                hr_img = upscale_net(teacher, lr_img, config.scale).clamp(0.0, 1.0)
                hr_img = back_project(hr_img, lr_img, config.scale)
            up = back_project(upscale_net(student, lr_img, config.scale), lr_img, config.scale)
            loss = interior_l1(up, hr_img, shave)
        else:
            up = upscale_net(student, lr_img, config.scale, first)
            if config.loss == "l1-backprojected":
                up = back_project(up, lr_img, config.scale)
            loss = interior_l1(up, hr_img, shave)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        decay = min(config.ema, (1.0 + step) / (10.0 + step))
        with torch.no_grad():
            for pe, p in zip(ema.parameters(), net.parameters(), strict=True):
                pe.lerp_(p, 1.0 - decay)
        run_loss, run_n = run_loss + float(loss.detach()), run_n + 1
        info: dict = {"loss": float(loss.detach())}
        done = step + 1
        if done % 25 == 0 or done % config.ckpt_every == 0 or done == config.steps:
            history.steps.append(done)
            history.loss.append(run_loss / run_n)
            run_loss, run_n = 0.0, 0
        if done % config.val_every == 0 or done == config.steps:
            val = validator(ema if calibration is None else FakeInt8(ema, calibration))  # type: ignore[arg-type]  # SRMD (TrainConfig.check)
            history.val_steps.append(done)
            for k, v in val.items():
                history.val_psnr.setdefault(k, []).append(v)
            mean = sum(val.values()) / max(1, len(val))
            info["val"] = mean
            if mean > history.best_psnr:
                history.best_psnr, history.best_step = mean, done
                weights.save_network(ema, best_file, config, {**meta, "step": str(done)})
        history.seconds = time.perf_counter() - t0
        if done % config.ckpt_every == 0 or done == config.steps:
            _save_atomic(
                {
                    "step": done,
                    "config": asdict(config),
                    "net": net.state_dict(),
                    "ema": ema.state_dict(),
                    "opt": opt.state_dict(),
                    "history": asdict(history),
                    "int8": None if calibration is None else calibration.to_json(),
                },
                ckpt,
            )
            (out_dir / HISTORY).write_text(json.dumps(asdict(history), indent=1))
        if progress is not None:
            progress(done, config.steps, info)
    return best_file, history
