"""Which image a glTF texture shows, and keeping its image extensions true to the images.

A texture names its image in its core ``source`` (PNG/JPEG) and/or in one of the image
extensions ``KHR_texture_basisu`` (KTX2), ``EXT_texture_avif`` and ``EXT_texture_webp``. A
viewer that supports the extension shows the extension's image, so that is the one pbrsr
upscales; the core ``source`` beside it is the fallback for other viewers and is written with
the same upscaled pixels. When several extensions are given, the first in
:data:`TEXTURE_EXTENSIONS`' order is taken.
"""

from __future__ import annotations

from collections.abc import Callable

from .gltf_read import get_index

TEXTURE_EXTENSIONS: dict[str, str] = {
    "KHR_texture_basisu": "image/ktx2",
    "EXT_texture_avif": "image/avif",
    "EXT_texture_webp": "image/webp",
}
"""glTF image extension -> the MIME type of the images it names."""
EXTENSION_OF_MIME: dict[str, str] = {mime: ext for ext, mime in TEXTURE_EXTENSIONS.items()}


def texture_sources(doc: dict, ti: int) -> tuple[int | None, int | None]:
    """``(image shown, fallback image)`` of texture ``ti``: the extension's image with the
    core ``source`` as its fallback, or the core ``source`` alone (fallback None); ``(None,
    None)`` when the texture names no image pbrsr reads. Indices are checked."""
    tex = doc["textures"][ti]
    n_images = len(doc.get("images", []))
    core = get_index(tex, "source", n_images, f"texture {ti}", required=False)
    exts = tex.get("extensions")
    if isinstance(exts, dict):
        for name in TEXTURE_EXTENSIONS:
            ext = exts.get(name)
            if isinstance(ext, dict) and "source" in ext:
                return get_index(ext, "source", n_images, f"texture {ti}'s {name}"), core
    return core, None


def fallback_images(doc: dict) -> dict[int, int]:
    """{fallback image: the extension image it stands in for} over every texture."""
    out: dict[int, int] = {}
    for ti in range(len(doc.get("textures", []))):
        shown, fallback = texture_sources(doc, ti)
        if shown is not None and fallback is not None and fallback != shown:
            out.setdefault(fallback, shown)
    return out


def sync_texture_extensions(doc: dict, mime_of: Callable[[int], str]) -> None:
    """Make every texture name each image where its format belongs, given each image's
    MIME type as written (``mime_of``): an extension whose image is now another extension's
    format moves to that extension, one whose image is now PNG/JPEG is dropped (its image
    becoming the core ``source`` when there is none), and a core ``source`` now in an
    extension's format moves into that extension. ``extensionsUsed`` and
    ``extensionsRequired`` then list these extensions exactly where a texture uses them (and,
    for required, has no core ``source``)."""
    for tex in doc.get("textures", []):
        exts = tex.get("extensions")
        if isinstance(exts, dict):
            for name in [n for n in TEXTURE_EXTENSIONS if n in exts]:
                ext = exts[name]
                if not isinstance(ext, dict) or not isinstance(ext.get("source"), int):
                    continue
                image = ext["source"]
                now = EXTENSION_OF_MIME.get(mime_of(image))
                if now == name:
                    continue
                del exts[name]
                if now is not None and now not in exts:
                    exts[now] = {**ext, "source": image}
                elif now is None and "source" not in tex:
                    tex["source"] = image
            if not exts:
                del tex["extensions"]
        core = tex.get("source")
        if isinstance(core, int):
            moved = EXTENSION_OF_MIME.get(mime_of(core))
            if moved is not None and moved not in (tex.get("extensions") or {}):
                tex.setdefault("extensions", {})[moved] = {"source": core}
                del tex["source"]
    used: set[str] = set()
    required: set[str] = set()
    for tex in doc.get("textures", []):
        for name in tex.get("extensions") or {}:
            if name in TEXTURE_EXTENSIONS:
                used.add(name)
                if "source" not in tex:
                    required.add(name)
    for key, names in (("extensionsUsed", used), ("extensionsRequired", required)):
        listed = [e for e in doc.get(key) or [] if e not in TEXTURE_EXTENSIONS or e in names]
        listed += sorted(names - set(listed))
        if listed:
            doc[key] = listed
        else:
            doc.pop(key, None)
