"""Rasterize a :class:`~pbrsr_core.asset.model.Mesh` for one :class:`Camera` into a sparse
G-buffer: only covered pixels are stored, so shading and its backward touch only them.

Only textures are optimised, so a G-buffer depends on (mesh, camera) alone: compute it once
per view and reuse it. Backends:

* ``"numba"``: CPU tiled z-buffer (:mod:`.raster_kernels`), the default on the CPU.
* ``"torch"``: vectorised torch kernel on the mesh's device; the reference path tests compare
  the others to, and the fallback on CUDA without nvdiffrast.
* ``"nvdiffrast"``: :mod:`.nvdiff`, used by ``"auto"`` only when ``nvdiffrast.torch`` imports
  and the mesh is on a CUDA device.

Conventions: pixel centres at +0.5, row 0 at the top. Every face is kept (double-sided
materials, thin geometry). A pixel that sees a face from behind (its geometric normal, from
the winding, points away from the eye) gets its whole shading frame mirrored: ``nrm``,
``tng.xyz`` and ``tng.w`` are negated, so the normal faces the viewer and a tangent-space
normal map is applied consistently. Triangles with a vertex behind the near plane
(``camera.NEAR`` in normalised units) or with non-finite positions are not drawn.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np
import torch

from ..asset.model import Mesh
from .camera import NEAR, Camera
from .raster_kernels import interpolate_numba, raster_numba, raster_torch

BACKENDS = ("auto", "numba", "torch", "nvdiffrast")


@dataclass
class GBuffer:
    """Per covered pixel (P of them) of one view, float32 unless stated.

    ``resolution`` (H, W); ``pix`` (P,) int64 flat row-major pixel index (ascending);
    ``tri`` (P,) int64 triangle index; ``bary`` (P, 3) perspective-correct barycentrics;
    ``pos`` (P, 3) world position; ``nrm`` (P, 3) unit interpolated normal, facing the
    viewer on back faces; ``tng`` (P, 4) unit tangent orthogonal to ``nrm`` + bitangent sign
    w (bitangent = w * cross(nrm, tng.xyz)); ``uv`` {texcoord: (P, 2)}; ``uv_grad``
    {texcoord: (P, 4)} = (du/dx, dv/dx, du/dy, dv/dy) per pixel (x right, y down);
    ``mat`` (P,) int64 material index (-1 = default material); ``view`` (P, 3) unit vector
    from the surface to the eye; ``backface`` (P,) bool."""

    resolution: tuple[int, int]
    pix: torch.Tensor
    tri: torch.Tensor
    bary: torch.Tensor
    pos: torch.Tensor
    nrm: torch.Tensor
    tng: torch.Tensor
    uv: dict[int, torch.Tensor] = field(default_factory=dict)
    uv_grad: dict[int, torch.Tensor] = field(default_factory=dict)
    mat: torch.Tensor | None = None
    view: torch.Tensor | None = None
    backface: torch.Tensor | None = None

    def __post_init__(self):
        # values derived from this G-buffer alone (texture taps, material rows), filled
        # lazily by the shader. Deliberately not a dataclass field: ``dataclasses.replace``,
        # :meth:`to` and code iterating ``fields()`` never see or copy it.
        self.cache: dict = {}

    def derived(self) -> dict:
        """The per-view cache, emptied if the pixels changed since it was filled."""
        if self.cache.get("_pix") is not self.pix:
            self.cache.clear()
            self.cache["_pix"] = self.pix
        return self.cache

    @property
    def num_pixels(self) -> int:
        return int(self.pix.shape[0])

    @property
    def device(self) -> torch.device:
        return self.pix.device

    def mask(self) -> torch.Tensor:
        """(H, W) bool coverage."""
        h, w = self.resolution
        m = torch.zeros(h * w, dtype=torch.bool, device=self.pix.device)
        m[self.pix] = True
        return m.view(h, w)

    def to(self, device: torch.device | str) -> GBuffer:
        kw = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, torch.Tensor):
                v = v.to(device)
            elif isinstance(v, dict):
                v = {k: t.to(device) for k, t in v.items()}
            kw[f.name] = v
        return GBuffer(**kw)


def nvdiffrast_available(device: torch.device | str) -> bool:
    """True when ``nvdiffrast.torch`` imports and ``device`` is CUDA."""
    if torch.device(device).type != "cuda":
        return False
    try:
        import nvdiffrast.torch  # noqa: F401
    except Exception:
        return False
    return True


def project(v_pos: torch.Tensor, camera: Camera) -> tuple[torch.Tensor, ...]:
    """Project (V, 3) positions: returns float64 ``clip`` (V, 4), ``sx, sy`` (V,) in pixels
    and ``iw`` (V,) = 1 / w_clip, on ``v_pos``'s device."""
    h, w = camera.resolution
    m = torch.as_tensor(camera.full_proj, dtype=torch.float64, device=v_pos.device)
    p = v_pos.double()
    clip = p @ m[:3, :3].T + m[:3, 3]
    clip = torch.cat([clip, (p @ m[3, :3] + m[3, 3])[:, None]], 1)
    iw = 1.0 / clip[:, 3]
    sx = (clip[:, 0] * iw + 1.0) * (0.5 * w)
    sy = (1.0 - clip[:, 1] * iw) * (0.5 * h)
    return clip, sx, sy, iw


def _drawable(mesh: Mesh, clip: torch.Tensor) -> torch.Tensor:
    """(T,) bool: all three vertices finite and in front of the near plane."""
    w = clip[:, 3]
    near = NEAR * 0.999  # world_to_cam includes the normalisation, so w is in unit-mesh units
    v_ok = torch.isfinite(clip).all(1) & (w > near)
    return v_ok[mesh.t_pos_idx].all(1)


def _safe_normalize(x: torch.Tensor, eps: float = 1e-20) -> tuple[torch.Tensor, torch.Tensor]:
    n2 = (x * x).sum(-1, keepdim=True)
    return x / n2.clamp_min(eps).sqrt(), n2 > eps


def _any_perpendicular(n: torch.Tensor) -> torch.Tensor:
    """(P, 3) a unit vector perpendicular to unit ``n``."""
    ref = torch.zeros_like(n)
    use_x = n[:, 0].abs() < 0.9
    ref[:, 0] = use_x.to(n.dtype)
    ref[:, 1] = (~use_x).to(n.dtype)
    t = ref - n * (n * ref).sum(-1, keepdim=True)
    return _safe_normalize(t)[0]


def build_gbuffer(
    mesh: Mesh, camera: Camera, pix: torch.Tensor, tri: torch.Tensor, bary: torch.Tensor
) -> GBuffer:
    """Interpolate the mesh attributes for covered pixels ``pix`` (P,) with triangle ids
    ``tri`` (P,) and perspective-correct barycentrics ``bary`` (P, 3), shared by every
    backend: the fused numba kernel on the CPU, :func:`build_gbuffer_torch` elsewhere."""
    if mesh.v_pos.device.type == "cpu":
        return _build_gbuffer_numba(mesh, camera, pix, tri, bary)
    return build_gbuffer_torch(mesh, camera, pix, tri, bary)


def _build_gbuffer_numba(mesh, camera, pix, tri, bary) -> GBuffer:
    h, w = camera.resolution
    P = int(pix.shape[0])
    keys = sorted(mesh.v_uv)
    n_v = mesh.v_pos.shape[0]
    v_uv = (
        torch.stack([mesh.v_uv[k].double() for k in keys]).numpy()
        if keys
        else np.zeros((0, n_v, 2))
    )
    _, sx, sy, iw = project(mesh.v_pos, camera)
    out = {
        "bary": np.empty((P, 3), np.float32),
        "pos": np.empty((P, 3), np.float32),
        "nrm": np.empty((P, 3), np.float32),
        "tng": np.empty((P, 4), np.float32),
        "uv": np.empty((len(keys), P, 2), np.float32),
        "uvg": np.empty((len(keys), P, 4), np.float32),
        "view": np.empty((P, 3), np.float32),
        "back": np.empty(P, np.bool_),
    }
    tri_np = tri.long().numpy()
    b = bary.float().numpy()
    interpolate_numba(
        pix.long().numpy(),
        tri_np,
        np.ascontiguousarray(b[:, 0]),
        np.ascontiguousarray(b[:, 1]),
        mesh.t_pos_idx.long().numpy(),
        mesh.v_pos.double().numpy(),
        mesh.v_nrm.double().numpy(),
        mesh.v_tng.double().numpy(),
        np.ascontiguousarray(v_uv),
        sx.numpy(),
        sy.numpy(),
        iw.numpy(),
        np.asarray(camera.eye, dtype=np.float64),
        w,
        out["bary"],
        out["pos"],
        out["nrm"],
        out["tng"],
        out["uv"],
        out["uvg"],
        out["view"],
        out["back"],
    )
    tri_t = tri.long()
    return GBuffer(
        resolution=(h, w),
        pix=pix.long(),
        tri=tri_t,
        bary=torch.from_numpy(out["bary"]),
        pos=torch.from_numpy(out["pos"]),
        nrm=torch.from_numpy(out["nrm"]),
        tng=torch.from_numpy(out["tng"]),
        uv={k: torch.from_numpy(out["uv"][i]) for i, k in enumerate(keys)},
        uv_grad={k: torch.from_numpy(out["uvg"][i]) for i, k in enumerate(keys)},
        mat=mesh.t_mat[tri_t].long(),
        view=torch.from_numpy(out["view"]),
        backface=torch.from_numpy(out["back"]),
    )


def build_gbuffer_torch(
    mesh: Mesh, camera: Camera, pix: torch.Tensor, tri: torch.Tensor, bary: torch.Tensor
) -> GBuffer:
    """Reference (and GPU) path of :func:`build_gbuffer` in plain torch, float64 inside."""
    dev = mesh.v_pos.device
    h, w = camera.resolution
    pix, tri = pix.to(dev).long(), tri.to(dev).long()
    b = bary.to(dev).double()
    idx = mesh.t_pos_idx[tri]  # (P, 3)

    def interp(attr: torch.Tensor) -> torch.Tensor:
        a = attr.double()
        return b[:, 0:1] * a[idx[:, 0]] + b[:, 1:2] * a[idx[:, 1]] + b[:, 2:3] * a[idx[:, 2]]

    pos = interp(mesh.v_pos)
    eye = torch.as_tensor(camera.eye, dtype=torch.float64, device=dev)
    view, _ = _safe_normalize(eye - pos, 1e-40)
    p0, p1, p2 = (mesh.v_pos[idx[:, k]].double() for k in range(3))
    gn, gn_ok = _safe_normalize(torch.cross(p1 - p0, p2 - p0, dim=-1), 1e-40)
    back = (gn * (eye - pos)).sum(-1) < 0.0

    nrm, n_ok = _safe_normalize(interp(mesh.v_nrm))
    fallback = torch.where(gn_ok, gn, view)
    nrm = torch.where(n_ok & torch.isfinite(nrm).all(-1, keepdim=True), nrm, fallback)
    t4 = interp(mesh.v_tng)
    t = t4[:, :3] - nrm * (nrm * t4[:, :3]).sum(-1, keepdim=True)
    t, t_ok = _safe_normalize(t, 1e-12)
    t_ok = t_ok & torch.isfinite(t).all(-1, keepdim=True)
    t = torch.where(t_ok, t, _any_perpendicular(nrm))
    sign = torch.where(t4[:, 3:4] < 0.0, -1.0, 1.0).to(t.dtype)
    flip = torch.where(back, -1.0, 1.0).to(t.dtype)[:, None]
    nrm, t, sign = nrm * flip, t * flip, sign * flip

    # screen-space UV derivatives (perspective-correct), see raster_kernels for conventions
    _, sx, sy, iw = project(mesh.v_pos, camera)
    X = torch.stack([sx[idx[:, k]] for k in range(3)], 1)
    Y = torch.stack([sy[idx[:, k]] for k in range(3)], 1)
    IW = torch.stack([iw[idx[:, k]] for k in range(3)], 1)
    area = (X[:, 1] - X[:, 0]) * (Y[:, 2] - Y[:, 0]) - (Y[:, 1] - Y[:, 0]) * (X[:, 2] - X[:, 0])
    area = torch.where(area.abs() > 1e-30, area, torch.full_like(area, 1e-30))
    dldx = torch.stack([Y[:, 1] - Y[:, 2], Y[:, 2] - Y[:, 0], Y[:, 0] - Y[:, 1]], 1) / area[:, None]
    dldy = torch.stack([X[:, 2] - X[:, 1], X[:, 0] - X[:, 2], X[:, 1] - X[:, 0]], 1) / area[:, None]
    wsum = (b / IW).sum(1, keepdim=True)  # = 1 / (interpolated 1/w)

    uv, uv_grad = {}, {}
    for k, tex in mesh.v_uv.items():
        u = interp(tex)  # (P, 2)
        tu = torch.stack([tex[idx[:, j]].double() for j in range(3)], 1)  # (P, 3, 2)
        diff = (tu - u[:, None, :]) * IW[:, :, None]
        ddx = (dldx[:, :, None] * diff).sum(1) * wsum
        ddy = (dldy[:, :, None] * diff).sum(1) * wsum
        g = torch.cat([ddx, ddy], 1)
        uv[k] = u.float()
        uv_grad[k] = torch.nan_to_num(g, nan=0.0, posinf=0.0, neginf=0.0).float()

    return GBuffer(
        resolution=(h, w),
        pix=pix,
        tri=tri,
        bary=b.float(),
        pos=pos.float(),
        nrm=nrm.float(),
        tng=torch.cat([t, sign], 1).float(),
        uv=uv,
        uv_grad=uv_grad,
        mat=mesh.t_mat[tri].long(),
        view=view.float(),
        backface=back,
    )


def coverage(mesh: Mesh, camera: Camera, backend: str = "auto"):
    """Run a coverage kernel only: returns ``tri`` (H*W,) int64 (-1 uncovered) and ``bary``
    (H*W, 3) float32 dense tensors on the mesh's device, plus the backend name used."""
    if backend not in BACKENDS:
        raise ValueError(f"unknown raster backend {backend!r}; choose one of {BACKENDS}")
    dev = mesh.v_pos.device
    h, w = camera.resolution
    if backend == "auto":
        if nvdiffrast_available(dev):
            backend = "nvdiffrast"
        else:
            backend = "numba" if dev.type == "cpu" else "torch"
    if backend == "nvdiffrast":
        from .nvdiff import raster_nvdiffrast

        tri, bary = raster_nvdiffrast(mesh, camera)
        return tri, bary, backend
    clip, sx, sy, iw = project(mesh.v_pos, camera)
    valid = _drawable(mesh, clip)
    if backend == "numba":
        out_tri, b0, b1 = raster_numba(
            sx.cpu().numpy(),
            sy.cpu().numpy(),
            iw.cpu().numpy(),
            mesh.t_pos_idx.cpu().numpy().astype(np.int64, copy=False),
            valid.cpu().numpy(),
            h,
            w,
        )
        out_tri, b0, b1 = (torch.from_numpy(a).to(dev) for a in (out_tri, b0, b1))
    else:
        out_tri, b0, b1 = raster_torch(sx, sy, iw, mesh.t_pos_idx.long(), valid, h, w)
    bary = torch.stack([b0, b1, 1.0 - b0 - b1], 1)
    return out_tri.long(), bary, backend


def rasterize(mesh: Mesh, camera: Camera, backend: str = "auto") -> GBuffer:
    """The sparse :class:`GBuffer` of ``mesh`` seen by ``camera``, on the mesh's device."""
    if mesh.num_triangles == 0:
        raise ValueError("cannot rasterize a mesh without triangles")
    tri, bary, _ = coverage(mesh, camera, backend)
    pix = torch.nonzero(tri >= 0).squeeze(1)
    return build_gbuffer(mesh, camera, pix, tri[pix], bary[pix])
