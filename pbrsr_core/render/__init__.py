"""The differentiable PBR renderer: cameras, a sparse G-buffer rasterizer, texture sampling,
split-sum environment lighting and GGX shading (see docs/ARCHITECTURE.md, "Render API").

Typical use::

    gb = raster.rasterize(mesh, cam)                 # once per view, cached
    rgba = shade.shade(gb, materials, textures, env)  # (P, 4), differentiable
                                                      # (``shade`` here is the module)
    img = shade.tonemap(shade.to_image(gb, rgba[:, :3], 0.0))
"""

from .camera import Camera, look_at, normalize_transform, orbit_cameras
from .light import EnvLight, brdf_lut
from .raster import GBuffer, rasterize
from .shade import to_image, tonemap  # shade.shade stays under its module name
from .texture import sample

__all__ = [
    "Camera",
    "EnvLight",
    "GBuffer",
    "brdf_lut",
    "look_at",
    "normalize_transform",
    "orbit_cameras",
    "rasterize",
    "sample",
    "to_image",
    "tonemap",
]
