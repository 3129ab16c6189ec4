"""Type checks of every glTF property the reader uses, before it uses any of them.

The glTF JSON comes from users: any value can have any type. Rather than guarding each read,
:func:`check_types` walks the document once against a small declarative schema (only the
properties pbrsr reads; unknown ones are ignored, as the spec asks) and raises InvalidAsset
naming the first bad property, e.g. ``materials[0].pbrMetallicRoughness.metallicFactor must be
a finite number``. Ranges that depend on other arrays (indices) are checked where they are
used (``gltf_read.get_index``).
"""

from __future__ import annotations

import math
from typing import Any

from ..errors import InvalidAsset

# leaf kinds: "index" int >= 0, "num" finite number, "str", "bool", "obj" any dict,
# "indices" list of "index", "nums" list of "num" ("numsN": exactly N), "strs" list of "str";
# a dict is a nested object schema; ("list", schema) a list of such objects;
# ("map", kind) a dict whose every value is of that kind.
Schema = dict[str, Any]

_EXT_OBJ = ("map", "obj")

TEXTURE_TRANSFORM: Schema = {
    "offset": "nums2",
    "rotation": "num",
    "scale": "nums2",
    "texCoord": "index",
}
TEXTURE_INFO: Schema = {
    "index": "index",
    "texCoord": "index",
    "scale": "num",
    "strength": "num",
    "extensions": {"KHR_texture_transform": TEXTURE_TRANSFORM},
}
PRIMITIVE: Schema = {
    "attributes": ("map", "index"),
    "indices": "index",
    "material": "index",
    "mode": "index",
    "targets": ("list", ("map", "index")),
    "extensions": _EXT_OBJ,
}
ACCESSOR: Schema = {
    "bufferView": "index",
    "byteOffset": "index",
    "componentType": "index",
    "normalized": "bool",
    "count": "index",
    "type": "str",
    "min": "nums",
    "max": "nums",
    "sparse": {
        "count": "index",
        "indices": {"bufferView": "index", "byteOffset": "index", "componentType": "index"},
        "values": {"bufferView": "index", "byteOffset": "index"},
    },
}
MATERIAL: Schema = {
    "pbrMetallicRoughness": {
        "baseColorFactor": "nums4",
        "baseColorTexture": TEXTURE_INFO,
        "metallicFactor": "num",
        "roughnessFactor": "num",
        "metallicRoughnessTexture": TEXTURE_INFO,
    },
    "normalTexture": TEXTURE_INFO,
    "occlusionTexture": TEXTURE_INFO,
    "emissiveTexture": TEXTURE_INFO,
    "emissiveFactor": "nums3",
    "alphaMode": "str",
    "alphaCutoff": "num",
    "doubleSided": "bool",
    "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": "num"}},
}
DOCUMENT: Schema = {
    "extensionsUsed": "strs",
    "extensionsRequired": "strs",
    "scene": "index",
    "scenes": ("list", {"nodes": "indices"}),
    "nodes": (
        "list",
        {
            "mesh": "index",
            "children": "indices",
            "matrix": "nums16",
            "translation": "nums3",
            "rotation": "nums4",
            "scale": "nums3",
        },
    ),
    "meshes": ("list", {"primitives": ("list", PRIMITIVE)}),
    "accessors": ("list", ACCESSOR),
    "bufferViews": (
        "list",
        {
            "buffer": "index",
            "byteOffset": "index",
            "byteLength": "index",
            "byteStride": "index",
            "target": "index",
        },
    ),
    "buffers": ("list", {"uri": "str", "byteLength": "index"}),
    "images": ("list", {"uri": "str", "mimeType": "str", "bufferView": "index"}),
    "textures": ("list", {"sampler": "index", "source": "index", "extensions": _EXT_OBJ}),
    "samplers": (
        "list",
        {"magFilter": "index", "minFilter": "index", "wrapS": "index", "wrapT": "index"},
    ),
    "materials": ("list", MATERIAL),
}

_DESCRIPTIONS = {
    "index": "a non-negative integer",
    "num": "a finite number",
    "str": "a string",
    "bool": "true or false",
    "obj": "an object",
    "indices": "an array of non-negative integers",
    "nums": "an array of finite numbers",
    "strs": "an array of strings",
}


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _leaf_ok(kind: str, v) -> bool:
    if kind == "index":
        return _is_int(v) and v >= 0
    if kind == "num":
        return _is_num(v)
    if kind == "str":
        return isinstance(v, str)
    if kind == "bool":
        return isinstance(v, bool)
    if kind == "obj":
        return isinstance(v, dict)
    if kind == "indices":
        return isinstance(v, list) and all(_is_int(x) and x >= 0 for x in v)
    if kind.startswith("nums"):
        n = int(kind[4:]) if kind[4:] else None
        return isinstance(v, list) and (n is None or len(v) == n) and all(_is_num(x) for x in v)
    if kind == "strs":
        return isinstance(v, list) and all(isinstance(x, str) for x in v)
    raise ValueError(kind)


def _fail(path: str, what: str):
    raise InvalidAsset(f"{path[:200]} in the glTF JSON must be {what}")


def _check(value, schema, path: str) -> None:
    if isinstance(schema, str):
        if not _leaf_ok(schema, value):
            if schema.startswith("nums") and schema != "nums":
                _fail(path, f"an array of {schema[4:]} finite numbers")
            _fail(path, _DESCRIPTIONS[schema])
    elif isinstance(schema, tuple) and schema[0] == "list":
        if not isinstance(value, list):
            _fail(path, "an array")
        for i, item in enumerate(value):
            _check(item, schema[1], f"{path}[{i}]")
    elif isinstance(schema, tuple) and schema[0] == "map":
        if not isinstance(value, dict):
            _fail(path, "an object")
        for k, v in value.items():
            _check(v, schema[1], f"{path}.{k}")
    else:
        if not isinstance(value, dict):
            _fail(path, "an object")
        for key, sub in schema.items():
            if key in value:
                _check(value[key], sub, f"{path}.{key}" if path else key)


def check_types(doc: dict) -> None:
    """Raise InvalidAsset unless every property pbrsr reads has its glTF type."""
    _check(doc, DOCUMENT, "")
