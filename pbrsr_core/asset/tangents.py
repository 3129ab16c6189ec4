"""Per-vertex tangent frames generated from positions, normals and UVs.

Per triangle, the tangent T and bitangent B solve ``[e1 e2] = [T B] [duv1 duv2]``; they are
accumulated (area-weighted: the unnormalised solution) onto the triangle's vertices, then T is
Gram-Schmidt orthogonalised against the vertex normal and the handedness sign
``w = sign(dot(cross(N, T), B))`` is stored in w (glTF: ``B = w * cross(N, T)``).

Guards (the result is never NaN): triangles with zero UV area (or zero area) contribute
nothing; a vertex whose accumulated tangent is (nearly) zero or parallel to its normal gets
any unit vector perpendicular to the normal; mirrored UV islands keep their own sign because
tangents are accumulated per vertex (vertices on a mirror seam are usually split by glTF
exporters, where they are not the dominant side wins).

UV convention: glTF (v down). The tangent follows +u and the bitangent +v in UV space as glTF's
normal-map convention expects when v is flipped; we use ``v' = 1 - v`` (OpenGL-style, v up) so
that a tangent-space normal map's +Y points along increasing image-up, as MikkTSpace does for
glTF.
"""

from __future__ import annotations

import numpy as np
import torch

_EPS = 1e-12


def any_perpendicular(n: np.ndarray) -> np.ndarray:
    """(V, 3) unit vectors perpendicular to the unit vectors ``n`` (V, 3)."""
    n = np.asarray(n, dtype=np.float64)
    axis = np.zeros_like(n)
    use_x = np.abs(n[:, 0]) < 0.9
    axis[use_x, 0] = 1.0
    axis[~use_x, 1] = 1.0
    t = np.cross(n, axis)
    ln = np.linalg.norm(t, axis=1, keepdims=True)
    t = np.where(ln > _EPS, t / np.maximum(ln, _EPS), np.array([1.0, 0.0, 0.0]))
    return t


def safe_normalize(v: np.ndarray, fallback: np.ndarray | None = None) -> np.ndarray:
    """Rows of ``v`` (N, 3) scaled to unit length; zero rows become ``fallback`` (or +z)."""
    v = np.asarray(v, dtype=np.float64)
    ln = np.linalg.norm(v, axis=1, keepdims=True)
    ok = ln > 1e-20
    out = v / np.where(ok, ln, 1.0)
    fb = np.array([0.0, 0.0, 1.0]) if fallback is None else fallback
    return np.where(ok, out, fb)


def vertex_normals(pos: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Smooth area-weighted vertex normals (V, 3) for positions (V, 3) and triangles (T, 3).
    Vertices only on zero-area triangles get +z."""
    pos = np.asarray(pos, dtype=np.float64)
    fn = np.cross(pos[tri[:, 1]] - pos[tri[:, 0]], pos[tri[:, 2]] - pos[tri[:, 0]])
    acc = np.zeros_like(pos)
    for k in range(3):
        np.add.at(acc, tri[:, k], fn)
    return safe_normalize(acc)


def generate_tangents(
    pos: np.ndarray, nrm: np.ndarray, uv: np.ndarray | None, tri: np.ndarray
) -> np.ndarray:
    """Tangents (V, 4) float32: xyz unit and perpendicular to ``nrm``, w = +-1.

    ``pos`` (V, 3), ``nrm`` (V, 3) unit, ``uv`` (V, 2) glTF UVs or None (then any frame
    perpendicular to the normal with w = 1), ``tri`` (T, 3) int vertex indices.
    """
    pos = np.asarray(pos, dtype=np.float64)
    nrm = safe_normalize(np.asarray(nrm, dtype=np.float64))
    tri = np.asarray(tri, dtype=np.int64).reshape(-1, 3)
    nv = pos.shape[0]
    tan = np.zeros((nv, 3))
    bit = np.zeros((nv, 3))
    if uv is not None and tri.shape[0] > 0:
        uvg = np.asarray(uv, dtype=np.float64).copy()
        uvg[:, 1] = 1.0 - uvg[:, 1]
        p0, p1, p2 = pos[tri[:, 0]], pos[tri[:, 1]], pos[tri[:, 2]]
        w0, w1, w2 = uvg[tri[:, 0]], uvg[tri[:, 1]], uvg[tri[:, 2]]
        e1, e2 = p1 - p0, p2 - p0
        d1, d2 = w1 - w0, w2 - w0
        det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
        good = np.isfinite(det) & (np.abs(det) > 1e-20)
        # area-weighted direction: scale by |e1 x e2| / |T| after solving; solve unnormalised
        r = np.where(good, 1.0 / np.where(good, det, 1.0), 0.0)[:, None]
        t = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) * r
        b = (e2 * d1[:, 0:1] - e1 * d2[:, 0:1]) * r
        area = np.linalg.norm(np.cross(e1, e2), axis=1, keepdims=True)
        t = safe_normalize(t, np.zeros(3)) * area
        b = safe_normalize(b, np.zeros(3)) * area
        t[~good] = 0.0
        b[~good] = 0.0
        for k in range(3):
            np.add.at(tan, tri[:, k], t)
            np.add.at(bit, tri[:, k], b)
    # Gram-Schmidt against the normal
    t_orth = tan - nrm * np.sum(nrm * tan, axis=1, keepdims=True)
    ln = np.linalg.norm(t_orth, axis=1, keepdims=True)
    ref = np.linalg.norm(tan, axis=1, keepdims=True)
    ok = (ln > 1e-8 * np.maximum(ref, 1e-30)) & (ln > 1e-20)
    fallback = any_perpendicular(nrm)
    t_unit = np.where(ok, t_orth / np.where(ok, ln, 1.0), fallback)
    w = np.where(np.sum(np.cross(nrm, t_unit) * bit, axis=1) < 0.0, -1.0, 1.0)
    out = np.concatenate([t_unit, w[:, None]], axis=1).astype(np.float32)
    return out


def generate_tangents_torch(
    v_pos: torch.Tensor, v_nrm: torch.Tensor, v_uv: torch.Tensor | None, t_idx: torch.Tensor
) -> torch.Tensor:
    """:func:`generate_tangents` on CPU tensors -> (V, 4) float32 tensor."""
    uv = None if v_uv is None else v_uv.detach().cpu().numpy()
    return torch.from_numpy(
        generate_tangents(
            v_pos.detach().cpu().numpy(),
            v_nrm.detach().cpu().numpy(),
            uv,
            t_idx.detach().cpu().numpy(),
        )
    )
