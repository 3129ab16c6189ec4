"""What a user asks of one upscale run; the same model serves the CLI, the API and the worker."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

DEFAULT_PRIOR = "pbr-srmd"
"""The image SR prior a run uses unless told otherwise: a shipped texture prior
(pbrsr_core/prior/texture.py; pbr-upconv7's networks, an SRMD network for colour maps at x4),
whose kinds without trained weights use waifu2x-photo."""

Method = Literal["pbrsr", "direct", "bicubic"]
LrKernel = Literal["gaussian", "area", "bicubic", "lanczos", "auto"]
OtherMaps = Literal["keep", "bicubic"]
ImageFormat = Literal["same", "png", "png16", "exr", "jpeg", "ktx2", "webp", "avif"]


class UpscaleOptions(BaseModel):
    """Options of one run. Unknown fields are refused, so a typo is an error, not a default."""

    model_config = ConfigDict(extra="forbid")

    scale: Literal[2, 4, 8] = Field(
        4, description="Upscaling factor of every texture (max_size may lower it per map)."
    )
    max_size: int | None = Field(
        None,
        ge=2,
        le=65536,
        description="Largest output texture side in pixels: a map that scale would make larger "
        "is upscaled by the largest of scale/2, scale/4 that fits, and kept as it is where x2 "
        "would not fit. None: every map at scale.",
    )
    maps: list[str] | None = Field(
        None,
        min_length=1,
        description="Material roles whose textures are upscaled (base_color, metallic_roughness, "
        "normal, occlusion, emissive, or a KHR_materials_* role such as clearcoat): an image is "
        "upscaled when any of its roles is listed, and every other image keeps its file. None: "
        "every map.",
    )
    other_maps: OtherMaps = Field(
        "keep",
        description="With maps: what the images of the unlisted roles get. keep: their files "
        "as they are; bicubic: a bicubic upscale at the factor a listed map would get (the "
        "prior and the optimiser skip them; PBR-SR renders them as they come out).",
    )
    method: Method = Field(
        "pbrsr",
        description="pbrsr: the PBR-SR optimizer; direct: the prior applied to each map; "
        "bicubic: plain bicubic interpolation.",
    )
    preset: str = Field("balanced", description="fast, balanced, quality or paper (pbrsr only).")
    iterations: int | None = Field(
        None,
        ge=0,
        le=100_000,
        description="Optimiser steps (pbrsr only); None: the preset's (fast, balanced and "
        "quality none, paper 2000). Steps run over the preset's views.",
    )
    prior: str = Field(
        DEFAULT_PRIOR,
        description="Image SR prior: pbr-upconv7, pbr-upconv7-fast, pbr-srmd, waifu2x-photo, "
        "rrdn-thick, bicubic, texture:<weights folder>, spandrel:<weights path>, "
        "diffusion:<model dir>.",
    )
    envmap: str | None = Field(
        None,
        description="Environment map for rendering: a .hdr/.exr path, or None for the "
        "built-in procedural environment.",
    )
    seed: int = Field(
        0, ge=0, description="Random seed; same seed and device give the same result."
    )
    image_format: ImageFormat = Field(
        "same",
        description="Output image format; 'same' keeps each input image's format and "
        "encoding (KTX2 codec, supercompression and transfer function; lossless WebP; bit "
        "depth never below the input's). ktx2, webp and avif put the textures in "
        "KHR_texture_basisu, EXT_texture_webp and EXT_texture_avif.",
    )
    lr_kernel: LrKernel = Field(
        "gaussian",
        description="How the input's maps were made from larger ones: the LR model the "
        "prior's back-projection and its checks one scale down invert. gaussian: blur, then "
        "bicubic (the evaluation protocol, pbrsr degrade); area: each texel the mean of its "
        "footprint (mipmaps); bicubic, lanczos: an image editor's antialiased resize; auto: "
        "the one the maps' spectra point to (pbrsr kernel estimate), named in the report.",
    )
    device: str = Field("auto", description="auto, cpu, cuda or cuda:N.")
    unwrap_missing_uvs: bool = Field(
        True, description="Unwrap meshes without UVs with xatlas; when false they are refused."
    )

    @field_validator("maps")
    @classmethod
    def _known_roles(cls, maps: list[str] | None) -> list[str] | None:
        from .asset.model import TEXTURE_ROLES  # the asset package imports torch

        if maps is None:
            return None
        unknown = [m for m in maps if m not in TEXTURE_ROLES]
        if unknown:
            raise ValueError(
                f"unknown map role {', '.join(map(repr, unknown))}: use {', '.join(TEXTURE_ROLES)}"
            )
        return sorted(set(maps), key=TEXTURE_ROLES.index)
