"""Which channels of an optimised image are which PBR map (glTF packing), and the weight each
map's consistency term gets."""

from __future__ import annotations

from .losses import MapGroup
from .presets import PbrsrConfig


def map_groups(roles: set[str], channels: int, config: PbrsrConfig) -> list[MapGroup]:
    """The PBR maps inside one image, from the roles that read it (glTF packing: occlusion R,
    roughness G, metallic B; colour and normal RGB). Channels beyond the image's are dropped."""
    spec: list[tuple[str, tuple[int, ...], float]] = []
    if "base_color" in roles:
        spec.append(("base_color", (0, 1, 2), config.w_other))
    if "emissive" in roles:
        spec.append(("emissive", (0, 1, 2), config.w_other))
    if "normal" in roles:
        spec.append(("normal", (0, 1, 2), config.w_other))
    if "occlusion" in roles:
        spec.append(("occlusion", (0,), config.w_other))
    if "metallic_roughness" in roles:
        spec.append(("roughness", (1,), config.w_other))
        spec.append(("metallic", (2,), config.w_metallic))
    out: list[MapGroup] = []
    taken: set[int] = set()
    for name, ch, w in spec:
        ch = tuple(c for c in ch if c < channels and c not in taken)
        if ch:
            taken.update(ch)
            out.append(MapGroup(name, ch, w))
    return out
