"""An asset made ready for the renderer: its mesh normalised to unit size and its maps in
optimisation space, plus helpers to render views of it (previews, evaluation)."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import torch

from .asset.model import Asset, Material, Mesh
from .maps import to_param
from .render import camera as cam
from .render import raster, shade
from .render.light import EnvLight


@dataclass
class Scene:
    mesh: Mesh  # normalised to unit size, on the scene's device
    materials: list[Material]
    device: torch.device


def make_scene(asset: Asset, device: torch.device) -> Scene:
    center, scale = cam.normalize_transform(asset.mesh.v_pos)
    mesh = asset.mesh
    c = torch.as_tensor(center, dtype=mesh.v_pos.dtype)
    normed = Mesh(
        v_pos=(mesh.v_pos - c) * scale,
        v_nrm=mesh.v_nrm,
        v_tng=mesh.v_tng,
        v_uv=mesh.v_uv,
        t_pos_idx=mesh.t_pos_idx,
        t_mat=mesh.t_mat,
    )
    return Scene(mesh=normed.to(device), materials=asset.materials, device=device)


@functools.lru_cache(maxsize=1)
def procedural_light() -> EnvLight:
    """The built-in environment, prefiltered once per process (a worker reuses it)."""
    return EnvLight.procedural()


@functools.lru_cache(maxsize=4)
def rotated_procedural_light(degrees: float) -> EnvLight:
    """The built-in environment turned about the up axis (an equirect map rolled in
    longitude), a second lighting for previews and relighting checks; cached per process."""
    from .render.envmaps import procedural_sky

    sky = procedural_sky()
    shift = int(round(degrees / 360.0 * sky.shape[1]))
    return EnvLight(torch.roll(sky, shifts=shift, dims=1), name=f"procedural-rot{degrees:g}")


def asset_textures(asset: Asset, device: torch.device) -> dict[int, torch.Tensor]:
    """Every image a material uses, in optimisation space, on ``device``."""
    return {img.index: to_param(img).to(device) for img in asset.images if img.roles}


def render_views(
    scene: Scene,
    textures: dict[int, torch.Tensor],
    cameras: list[cam.Camera],
    light: EnvLight,
    *,
    background: float = 0.0,
    gbuffers: list[raster.GBuffer] | None = None,
) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """Render ``cameras`` of the scene: sRGB images (H, W, 3) in [0, 1] and coverage masks
    (H, W) bool. ``gbuffers`` may be passed to reuse rasterisations of the same cameras."""
    images, masks = [], []
    bg = torch.full((3,), float(background), device=scene.device)
    with torch.no_grad():
        for i, c in enumerate(cameras):
            gb = gbuffers[i] if gbuffers is not None else raster.rasterize(scene.mesh, c)
            gb = gb.to(scene.device)
            rgba = shade.shade(gb, scene.materials, textures, light)
            srgb = shade.tonemap(rgba[:, :3])
            images.append(shade.to_image(gb, srgb, bg))
            h, w = gb.resolution
            m = torch.zeros(h * w, dtype=torch.bool, device=scene.device)
            m[gb.pix] = True
            masks.append(m.view(h, w))
    return images, masks
