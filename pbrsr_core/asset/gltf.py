"""Load ``.glb``/``.gltf`` assets into :class:`~pbrsr_core.asset.model.Asset` and save them back
with chosen images replaced, losing nothing else.

Loading keeps the parsed JSON untouched in ``Asset.document`` and derives the typed views:
the merged world-space :class:`Mesh` of the default scene, every :class:`Material` with
resolved :class:`TextureRef`s, and every image decoded. Saving edits the JSON (only the entries
of replaced images and their bufferViews change) and writes atomically inside the output's
folder; see :mod:`pbrsr_core.asset.gltf_write`. Materials are read by
:mod:`~pbrsr_core.asset.gltf_materials`, the scene's mesh built by
:mod:`~pbrsr_core.asset.gltf_scene`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np

from ..errors import InvalidAsset, LimitExceeded, UnprocessableAsset, UnsupportedAsset
from ..limits import Limits
from .gltf_materials import read_material
from .gltf_read import (
    GLB_MAGIC,
    buffer_view_bytes,
    check_buffer_views,
    load_buffers,
    parse_glb,
    parse_json,
)
from .gltf_scene import SceneBuilder, scene_roots
from .gltf_write import encode_images, save_asset
from .images import read_texture
from .jpeg import quant_tables
from .mesh_codecs import decode_geometry, meshopt_placeholders, placeholder_extent
from .model import (
    SRGB_ROLES,
    Asset,
    ImageData,
)
from .texture_codecs import Ktx2Encoding, transfer
from .uris import decode_data_uri, is_data_uri, read_resource, relative_path, safe_stem

__all__ = ["encode_images", "image_by_index", "load_asset", "save_asset"]


def _image_label(img: dict, i: int, default_ext: str = "") -> str:
    uri = img.get("uri")
    if isinstance(uri, str) and not is_data_uri(uri):
        return str(relative_path(uri, f"image {i}"))
    name = img.get("name")
    return f"{safe_stem(name if isinstance(name, str) else '', f'image{i}')}{default_ext}"


def _load_images(
    doc: dict,
    folder: Path,
    buffers: list[bytes],
    limits: Limits,
    resources: dict[str, bytes],
    roles: dict[int, set[str]],
) -> list[ImageData]:
    """Every image decoded, with the material roles that use it (``roles``)."""
    out = []
    for i, img in enumerate(doc.get("images", [])):
        what = f"image {i}"
        label = _image_label(img, i)
        uri = img.get("uri")
        if "bufferView" in img:
            data = buffer_view_bytes(doc, buffers, img["bufferView"], what)
        elif isinstance(uri, str):
            if is_data_uri(uri):
                data, _ = decode_data_uri(uri, limits.max_data_uri_bytes, what)
            else:
                data = read_resource(folder, uri, limits.max_file_bytes, what)
                resources[label] = data
        else:
            raise InvalidAsset(f"{what} has neither a uri nor a bufferView")
        used_as = roles.get(i, set())
        try:
            pixels, depth, mime, encoding = read_texture(data, label, limits)
        except (UnsupportedAsset, InvalidAsset):
            if used_as:
                raise
            # an image no material slot uses and pbrsr cannot decode (e.g. the DDS image of
            # MSFT_texture_dds): kept as an empty placeholder, saved byte for byte
            declared = img.get("mimeType")
            pixels = np.zeros((0, 0, 4), dtype=np.float32)
            depth, mime = 8, declared if isinstance(declared, str) else "application/octet-stream"
            encoding = None
        if isinstance(encoding, Ktx2Encoding):
            pixels = transfer(pixels, encoding.srgb, bool(used_as & SRGB_ROLES))
        jpeg = quant_tables(data) if mime == "image/jpeg" else None
        out.append(
            ImageData(
                index=i,
                name=label,
                pixels=pixels,
                bit_depth=depth,
                mime=mime,
                roles=set(used_as),
                jpeg=jpeg,
                encoding=encoding,
            )
        )
    return out


# ----------------------------------------------------------------------------- geometry
def load_asset(path: Path, limits: Limits = Limits(), *, unwrap_missing_uvs: bool = True) -> Asset:
    """Read a ``.glb`` or ``.gltf`` file (the kind is taken from the bytes, not the name).

    External files are resolved relative to the file's folder and must stay inside it.
    Raises InvalidAsset / UnsupportedAsset / LimitExceeded / UnprocessableAsset with a message
    naming the glTF object at fault.
    """
    path = Path(path)
    if not path.is_file():
        raise InvalidAsset(f"the file '{path.name}' does not exist")
    size = path.stat().st_size
    if size == 0:
        raise InvalidAsset(f"the file '{path.name}' is empty")
    if size > limits.max_file_bytes:
        raise LimitExceeded(
            f"the file '{path.name}' is {size} bytes; the limit is {limits.max_file_bytes}"
        )
    raw = path.read_bytes()
    kind: Literal["glb", "gltf"]
    if raw[:4] == GLB_MAGIC:
        doc, bin_chunk = parse_glb(raw)
        kind = "glb"
    else:
        head = raw[:64].lstrip(b"\xef\xbb\xbf \t\r\n")
        if not head.startswith(b"{"):
            raise UnsupportedAsset(
                f"the file '{path.name}' is neither glTF JSON nor GLB (nor a zip of them)"
            )
        doc, bin_chunk = parse_json(raw), None
        kind = "gltf"
    del raw
    folder = path.parent
    resources: dict[str, bytes] = {}
    placeholders = {
        i: placeholder_extent(doc, i, limits) for i in meshopt_placeholders(doc, kind == "glb")
    }
    buffers = load_buffers(doc, folder, bin_chunk, kind == "glb", limits, resources, placeholders)
    check_buffer_views(doc, buffers)
    geometry = decode_geometry(doc, buffers, set(placeholders), limits)

    materials = [read_material(doc, i) for i in range(len(doc.get("materials", [])))]
    roles: dict[int, set[str]] = {}
    for m in materials:
        for role, ref in m.textures().items():
            roles.setdefault(ref.image, set()).add(role)
    builder = SceneBuilder(doc, buffers, limits, unwrap_missing_uvs, geometry)
    builder.walk(scene_roots(doc))
    mesh = builder.build()
    decoded_buffers = geometry.buffers if geometry else buffers  # meshopt views decoded
    images = _load_images(doc, folder, decoded_buffers, limits, resources, roles)
    asset = Asset(
        document=doc,
        buffers=buffers,
        images=images,
        materials=materials,
        mesh=mesh,
        source=path,
        kind=kind,
        resources=resources,
        generated_uvs=dict(builder.unwrapped),
        geometry=geometry,
    )
    if builder.missing_uv:
        mi, pi, n = builder.missing_uv[0]
        raise UnprocessableAsset(
            f"mesh {mi} primitive {pi} has a textured material that needs TEXCOORD_{n}, "
            "which it lacks: turn on unwrapping to generate UVs (or add UVs in a DCC tool)"
        )
    return asset


def image_by_index(asset: Asset, index: int) -> ImageData:
    """The decoded image with glTF index ``index``."""
    for im in asset.images:
        if im.index == index:
            return im
    raise KeyError(index)
