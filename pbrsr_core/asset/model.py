"""The in-memory model of a glTF asset that every other module works on.

The glTF JSON is kept as parsed (``Asset.document``) so that writing the asset back loses
nothing; the typed views below (materials, merged mesh, decoded images) are derived from it.
Conventions, used everywhere in pbrsr:

* Images are ``numpy`` arrays ``(H, W, C)`` float32, row 0 at the top, values in [0, 1] *as
  stored in the file* (baseColor/emissive stay sRGB-encoded here; linearisation happens once,
  in ``pbrsr_core.colour``, where maps become optimisation parameters).
* UVs follow glTF: (0, 0) is the top-left corner of the image, u to the right, v down, so
  texel ``(x, y)`` has its centre at ``((x + 0.5) / W, (y + 0.5) / H)``.
* A glTF image is the unit of work: a texture shared by several materials is one image, one
  parameter, processed once.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from .jpeg import JpegQuant
from .texture_codecs import TextureEncoding

MapRole = Literal["base_color", "metallic_roughness", "normal", "occlusion", "emissive"]
MAP_ROLES: tuple[MapRole, ...] = (
    "base_color",
    "metallic_roughness",
    "normal",
    "occlusion",
    "emissive",
)
# Textures of the KHR_materials_* extensions: role -> (extension, key, what the data is).
# The renderer models none of them; they are upscaled as maps of their kind and written back.
EXTENSION_ROLES: dict[str, tuple[str, str, str]] = {
    "clearcoat": ("KHR_materials_clearcoat", "clearcoatTexture", "data"),
    "clearcoat_roughness": ("KHR_materials_clearcoat", "clearcoatRoughnessTexture", "data"),
    "clearcoat_normal": ("KHR_materials_clearcoat", "clearcoatNormalTexture", "normal"),
    "sheen_color": ("KHR_materials_sheen", "sheenColorTexture", "colour"),
    "sheen_roughness": ("KHR_materials_sheen", "sheenRoughnessTexture", "data"),
    "specular": ("KHR_materials_specular", "specularTexture", "data"),
    "specular_color": ("KHR_materials_specular", "specularColorTexture", "colour"),
    "transmission": ("KHR_materials_transmission", "transmissionTexture", "data"),
    "thickness": ("KHR_materials_volume", "thicknessTexture", "data"),
    "iridescence": ("KHR_materials_iridescence", "iridescenceTexture", "data"),
    "iridescence_thickness": (
        "KHR_materials_iridescence",
        "iridescenceThicknessTexture",
        "data",
    ),
    "anisotropy": ("KHR_materials_anisotropy", "anisotropyTexture", "data"),
    "diffuse_transmission": (
        "KHR_materials_diffuse_transmission",
        "diffuseTransmissionTexture",
        "data",
    ),
    "diffuse_transmission_color": (
        "KHR_materials_diffuse_transmission",
        "diffuseTransmissionColorTexture",
        "colour",
    ),
}
EXTENSION_CHANNELS: dict[str, tuple[int, ...]] = {
    "clearcoat": (0,),
    "clearcoat_roughness": (1,),
    "sheen_roughness": (),
    "specular": (),
    "transmission": (0,),
    "thickness": (1,),
    "iridescence": (0,),
    "iridescence_thickness": (1,),
    "anisotropy": (0, 1, 2),
    "diffuse_transmission": (),
}
"""The colour channels (R, G, B: 0, 1, 2) each KHR_materials_* data map's role reads, as the
extensions specify; sheen roughness, specular and diffuse transmission read alpha only."""
TEXTURE_ROLES: tuple[str, ...] = (*MAP_ROLES, *EXTENSION_ROLES)
"""Every material role a texture can have: the core glTF maps, then the KHR_materials_* ones."""
SRGB_ROLES: frozenset[str] = frozenset(
    {"base_color", "emissive"} | {r for r, (_, _, k) in EXTENSION_ROLES.items() if k == "colour"}
)
NORMAL_ROLES: frozenset[str] = frozenset(
    {"normal"} | {r for r, (_, _, k) in EXTENSION_ROLES.items() if k == "normal"}
)

REPEAT, CLAMP_TO_EDGE, MIRRORED_REPEAT = 10497, 33071, 33648


@dataclass(frozen=True)
class TextureRef:
    """One material slot's reference to an image, fully resolved.

    ``uv_transform`` is the row-major 3x3 matrix of ``KHR_texture_transform`` (offset,
    rotation, scale) applied to homogeneous UVs ``(u, v, 1)``; ``None`` means identity.
    ``texcoord`` already honours the extension's ``texCoord`` override.
    """

    image: int
    texcoord: int = 0
    uv_transform: tuple[float, ...] | None = None
    wrap_s: int = REPEAT
    wrap_t: int = REPEAT
    mag_filter: int | None = None
    min_filter: int | None = None


@dataclass
class Material:
    """A glTF metallic-roughness material. Factors are linear (glTF stores them linear)."""

    index: int
    name: str = ""
    base_color_factor: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)
    base_color: TextureRef | None = None
    metallic_factor: float = 1.0
    roughness_factor: float = 1.0
    metallic_roughness: TextureRef | None = None  # G = roughness, B = metallic
    normal: TextureRef | None = None
    normal_scale: float = 1.0
    occlusion: TextureRef | None = None  # R channel
    occlusion_strength: float = 1.0
    emissive_factor: tuple[float, float, float] = (0.0, 0.0, 0.0)
    emissive: TextureRef | None = None
    emissive_strength: float = 1.0  # KHR_materials_emissive_strength
    alpha_mode: Literal["OPAQUE", "MASK", "BLEND"] = "OPAQUE"
    alpha_cutoff: float = 0.5
    double_sided: bool = False
    extension_textures: dict[str, TextureRef] = field(default_factory=dict)
    """Textures of KHR_materials_* extensions by role (:data:`EXTENSION_ROLES`)."""

    def texture(self, role: MapRole) -> TextureRef | None:
        return getattr(self, role)

    def textures(self) -> dict[str, TextureRef]:
        """Every texture the material uses, by role (core and extension ones)."""
        out: dict[str, TextureRef] = {}
        for role in MAP_ROLES:
            ref = self.texture(role)
            if ref is not None:
                out[role] = ref
        return {**out, **self.extension_textures}


DEFAULT_MATERIAL = Material(index=-1, name="default")


@dataclass
class Mesh:
    """Every triangle primitive of the default scene, merged, in world space.

    Shapes: ``v_pos`` (V, 3), ``v_nrm`` (V, 3) unit, ``v_tng`` (V, 4) with xyz unit and w the
    bitangent sign (generated from UVs where the asset has none), ``v_uv[n]`` (V, 2) for each
    TEXCOORD_n present, ``t_pos_idx`` (T, 3) int64, ``t_mat`` (T,) int64 index into
    ``Asset.materials`` (-1 for the glTF default material). All float tensors are float32 on
    the CPU; callers move them with :meth:`to`.
    """

    v_pos: torch.Tensor
    v_nrm: torch.Tensor
    v_tng: torch.Tensor
    v_uv: dict[int, torch.Tensor]
    t_pos_idx: torch.Tensor
    t_mat: torch.Tensor

    @property
    def num_triangles(self) -> int:
        return int(self.t_pos_idx.shape[0])

    def to(self, device: torch.device | str) -> Mesh:
        return Mesh(
            v_pos=self.v_pos.to(device),
            v_nrm=self.v_nrm.to(device),
            v_tng=self.v_tng.to(device),
            v_uv={k: v.to(device) for k, v in self.v_uv.items()},
            t_pos_idx=self.t_pos_idx.to(device),
            t_mat=self.t_mat.to(device),
        )


@dataclass
class ImageData:
    """One decoded glTF image.

    ``pixels`` (H, W, C) float32 in [0, 1] as stored (see module docstring); ``bit_depth`` is
    8, 16 or 32 (float); ``mime`` is the source type ("image/png", "image/jpeg",
    "image/x-exr", "image/tiff", "image/ktx2", "image/webp", "image/avif"); ``roles`` lists the
    material slots that use the image. ``name`` is a safe, asset-relative label for messages
    and output file names.
    ``jpeg``: a JPEG file's quantisation tables and chroma sampling (``asset.jpeg``), else None.
    ``encoding``: how a KTX2 or WebP file is encoded (``asset.texture_codecs``), else None;
    a KTX2 image's pixels are in its role's colour space even where its DFD says otherwise.
    """

    index: int
    name: str
    pixels: np.ndarray
    bit_depth: int
    mime: str
    roles: set[str] = field(default_factory=set)
    jpeg: JpegQuant | None = None
    encoding: TextureEncoding | None = None

    @property
    def height(self) -> int:
        return int(self.pixels.shape[0])

    @property
    def width(self) -> int:
        return int(self.pixels.shape[1])

    @property
    def channels(self) -> int:
        return int(self.pixels.shape[2])


@dataclass
class UnwrappedPrimitive:
    """A primitive re-indexed by UV unwrapping (see :mod:`pbrsr_core.asset.unwrap`).

    ``vmapping`` (V',) int64: the original vertex each new vertex copies; ``indices`` (T, 3)
    int64: the primitive's triangles over the new vertices, in the original triangle order
    (strips and fans become lists); ``uvs`` {texcoord n: (V', 2) float32}: the generated sets.
    """

    vmapping: np.ndarray
    indices: np.ndarray
    uvs: dict[int, np.ndarray]


@dataclass
class DecodedGeometry:
    """Compressed geometry decoded for reading (see :mod:`pbrsr_core.asset.mesh_codecs`).

    ``buffers``: the asset's buffers with every ``EXT_meshopt_compression`` bufferView decoded
    into place (the asset's own ``buffers`` keep the bytes of the file, which saving writes);
    ``accessors`` {accessor index: (count, ncomp) array of its component type}: the data of
    the accessors that ``KHR_draco_mesh_compression`` primitives fill.
    """

    buffers: list[bytes]
    accessors: dict[int, np.ndarray] = field(default_factory=dict)


@dataclass
class Asset:
    """A loaded asset: the untouched glTF document plus typed views of it."""

    document: dict
    buffers: list[bytes]
    images: list[ImageData]
    materials: list[Material]
    mesh: Mesh
    source: Path
    kind: Literal["glb", "gltf"]
    # Raw bytes of every external file the document refers to, by its (decoded) relative
    # path, so that saving copies unchanged files byte for byte even when the source is gone.
    resources: dict[str, bytes] = field(default_factory=dict)
    # Primitives unwrapped because they lacked a TEXCOORD their material needs:
    # {(mesh index, primitive index): UnwrappedPrimitive}; saving writes each as a re-indexed
    # primitive (every attribute gathered, new indices, new TEXCOORD accessors).
    generated_uvs: dict[tuple[int, int], UnwrappedPrimitive] = field(default_factory=dict)
    # Draco and meshopt geometry decoded; None when the asset has no compressed geometry.
    geometry: DecodedGeometry | None = None

    def material(self, index: int) -> Material:
        return DEFAULT_MATERIAL if index < 0 else self.materials[index]
