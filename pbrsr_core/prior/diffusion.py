"""``diffusion:<model dir>``: diffusers' ``StableDiffusionUpscalePipeline`` (the Stable
Diffusion x4 upscaler) from a LOCAL directory, for farms with GPUs.

Never downloads: the pipeline is loaded with ``local_files_only=True`` from a directory saved
with ``save_pretrained`` (or a hub snapshot copied there). ``diffusers`` (and ``transformers``,
for its text encoder) are imported only when this prior is asked for; without them,
:class:`PriorUnavailable` names what to install. Each tile is denoised with a generator seeded
from ``seed``, so runs repeat. The model works at 128x128 LR tiles (512 output), its training
size.
"""

from __future__ import annotations

import threading
from pathlib import Path

import torch

from ..errors import InvalidOptions, PriorUnavailable
from .base import Prior

INSTALL_HINT = "pip install diffusers transformers"


class DiffusionPrior(Prior):
    """Stable Diffusion x4 upscaling; images in and out are sRGB in [0, 1]."""

    scales = (4,)
    bytes_per_pixel = 1 << 17  # UNet attention at 4x: keep tiles near the training size
    default_overlap = 16

    def __init__(
        self,
        model_dir: Path,
        device: torch.device | str = "cpu",
        *,
        steps: int = 20,
        noise_level: int = 20,
        guidance_scale: float = 0.0,
        prompt: str = "high quality detailed texture",
        seed: int = 0,
    ) -> None:
        super().__init__()
        self.device = torch.device(device)
        model_dir = Path(model_dir)
        self.name = f"diffusion:{model_dir.name}"
        try:
            from diffusers import StableDiffusionUpscalePipeline
        except ImportError as exc:
            raise PriorUnavailable(
                f"the diffusion prior needs the diffusers library: {INSTALL_HINT}"
            ) from exc
        if not (model_dir / "model_index.json").is_file():
            raise InvalidOptions(
                f"'{model_dir.name}' is not a local diffusers model directory (no "
                "model_index.json); save the Stable Diffusion x4 upscaler there first"
            )
        dtype = torch.float16 if self.device.type == "cuda" else torch.float32
        try:
            pipe = StableDiffusionUpscalePipeline.from_pretrained(
                str(model_dir), local_files_only=True, torch_dtype=dtype
            )
        except (OSError, ValueError) as exc:
            raise InvalidOptions(f"cannot load the diffusion model '{model_dir.name}'") from exc
        pipe = pipe.to(self.device)
        pipe.set_progress_bar_config(disable=True)
        self.pipe = pipe
        self.steps, self.noise_level, self.guidance_scale = steps, noise_level, guidance_scale
        self.prompt, self.seed = prompt, seed
        self.tile_size = 128
        self._lock = threading.Lock()

    def num_parameters(self) -> int:
        return sum(
            p.numel()
            for part in (self.pipe.unet, self.pipe.vae, self.pipe.text_encoder)
            if part is not None
            for p in part.parameters()
        )

    def _forward(self, x: torch.Tensor, scale: int) -> torch.Tensor:
        """x (B, 3, h, w) in [0, 1] -> (B, 3, 4h, 4w) in [0, 1]."""
        gen = torch.Generator(device=self.device).manual_seed(self.seed)
        with self._lock:
            out = self.pipe(
                prompt=[self.prompt] * x.shape[0],
                image=x.to(self.pipe.unet.dtype),
                num_inference_steps=self.steps,
                guidance_scale=self.guidance_scale,
                noise_level=self.noise_level,
                generator=gen,
                output_type="pt",
            ).images
        return out.float().to(x.device)
