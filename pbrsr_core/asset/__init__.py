"""Asset I/O that loses nothing: glTF/GLB load and save, texture files, safe zip extraction,
procedural assets and the Khronos glTF-Validator. See docs/ARCHITECTURE.md."""

from .archive import detect_kind, extract_zip
from .gltf import encode_images, load_asset, save_asset
from .images import EncodedImage, encode_image, output_format, read_image, write_image
from .model import (
    MAP_ROLES,
    SRGB_ROLES,
    Asset,
    ImageData,
    MapRole,
    Material,
    Mesh,
    TextureRef,
)
from .procedural import make_cutout_asset, make_demo_asset, make_quad_asset, make_test_asset
from .validator import validate_gltf

__all__ = [
    "MAP_ROLES",
    "SRGB_ROLES",
    "Asset",
    "ImageData",
    "MapRole",
    "Material",
    "Mesh",
    "TextureRef",
    "detect_kind",
    "EncodedImage",
    "encode_image",
    "encode_images",
    "extract_zip",
    "load_asset",
    "make_cutout_asset",
    "make_demo_asset",
    "make_quad_asset",
    "make_test_asset",
    "output_format",
    "read_image",
    "save_asset",
    "validate_gltf",
    "write_image",
]
