"""Small procedural meshes for renderer tests and benchmarks (no asset I/O involved).

Both meshes carry glTF-style attributes: unit normals, tangents with ``w`` such that the
bitangent ``w * cross(n, t)`` points toward decreasing v (up in the image, OpenGL +Y normal
maps), and TEXCOORD_0 with (0, 0) at the image's top-left.
"""

from __future__ import annotations

import math

import torch

from ..asset.model import Mesh


def quad(size: float = 1.0, z: float = 0.0, n_sub: int = 1, material: int = 0) -> Mesh:
    """A square in the plane ``z``, normal +z, side ``size``, centred on the origin, split
    into ``n_sub x n_sub`` cells (2 triangles each). u follows +x, v follows -y."""
    n = n_sub + 1
    s = torch.linspace(0.0, 1.0, n, dtype=torch.float64)
    v_grid, u_grid = torch.meshgrid(s, s, indexing="ij")
    u, v = u_grid.reshape(-1), v_grid.reshape(-1)
    pos = torch.stack([(u - 0.5) * size, (0.5 - v) * size, torch.full_like(u, z)], 1)
    nrm = torch.tensor([[0.0, 0.0, 1.0]]).expand(n * n, 3)
    tng = torch.tensor([[1.0, 0.0, 0.0, 1.0]]).expand(n * n, 4)
    ij = torch.arange(n_sub)
    r, c = torch.meshgrid(ij, ij, indexing="ij")
    a = (r * n + c).reshape(-1)
    b, cc, d = a + 1, a + n, a + n + 1
    # counter-clockwise seen from +z (v grows downward, so rows go -y)
    tris = torch.cat([torch.stack([a, cc, b], 1), torch.stack([b, cc, d], 1)], 0)
    return Mesh(
        v_pos=pos.float(),
        v_nrm=nrm.float().contiguous(),
        v_tng=tng.float().contiguous(),
        v_uv={0: torch.stack([u, v], 1).float()},
        t_pos_idx=tris.long(),
        t_mat=torch.full((tris.shape[0],), material, dtype=torch.long),
    )


def uv_sphere(n_lat: int = 16, n_lon: int = 32, radius: float = 0.5, material: int = 0) -> Mesh:
    """A latitude/longitude sphere centred on the origin with ``2 * n_lon * (n_lat - 1)``
    triangles. u = longitude / 2 pi (from +z toward +x), v = polar angle from +y / pi."""
    if n_lat < 2 or n_lon < 3:
        raise ValueError("uv_sphere needs n_lat >= 2 and n_lon >= 3")
    th = torch.linspace(0.0, math.pi, n_lat + 1, dtype=torch.float64)
    ph = torch.linspace(0.0, 2.0 * math.pi, n_lon + 1, dtype=torch.float64)
    T, P = torch.meshgrid(th, ph, indexing="ij")
    T, P = T.reshape(-1), P.reshape(-1)
    nrm = torch.stack([T.sin() * P.sin(), T.cos(), T.sin() * P.cos()], 1)
    tng = torch.stack([P.cos(), torch.zeros_like(P), -P.sin(), torch.ones_like(P)], 1)
    uv = torch.stack([P / (2.0 * math.pi), T / math.pi], 1)
    m = n_lon + 1
    tris = []
    for i in range(n_lat):
        for j in range(n_lon):
            a, b = i * m + j, i * m + j + 1
            c, d = a + m, b + m
            if i > 0:
                tris.append((a, c, b))
            if i < n_lat - 1:
                tris.append((b, c, d))
    t = torch.tensor(tris, dtype=torch.long)
    return Mesh(
        v_pos=(nrm * radius).float(),
        v_nrm=nrm.float(),
        v_tng=tng.float(),
        v_uv={0: uv.float()},
        t_pos_idx=t,
        t_mat=torch.full((t.shape[0],), material, dtype=torch.long),
    )
