"""Plain PyTorch reference backend (autograd, any device). It is the oracle in tests.

Same math as the numba kernels (see ``numba_raster`` for the compositing rule), written with
dense tensor ops: per 16x16 tile, every Gaussian whose rectangle meets the tile is evaluated on
every pixel of the tile (``tile_size=None`` evaluates every Gaussian on every pixel).
"""

from __future__ import annotations

import torch

from .numba_project import BLUR
from .numba_raster import ALPHA_MAX, ALPHA_MIN, T_MIN


def _quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    n = quats.norm(dim=-1, keepdim=True)
    small = n < 1e-12
    q = quats / torch.where(small, torch.ones_like(n), n)
    ident = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=quats.dtype, device=quats.device)
    q = torch.where(small, ident.expand_as(q), q)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(quats.shape[:-1] + (3, 3))


def project(means, quats, scales, opacities, viewmats, Ks, width, height, near, far, eps2d=BLUR):
    """EWA projection; returns means2d [C,N,2], conics [C,N,3], depths [C,N], radii [C,N,2]
    int32 and rects [C,N,4] int32 (see ``numba_project``)."""
    R = _quat_to_rotmat(quats)  # [N,3,3]
    M = R * scales[:, None, :]  # R S
    Rw = viewmats[:, :3, :3]  # [C,3,3]
    tw = viewmats[:, :3, 3]
    p = torch.einsum("cij,nj->cni", Rw, means) + tw[:, None, :]  # [C,N,3]
    px, py, pz = p.unbind(-1)
    fx = Ks[:, 0, 0][:, None]
    fy = Ks[:, 1, 1][:, None]
    cx = Ks[:, 0, 2][:, None]
    cy = Ks[:, 1, 2][:, None]
    valid = (pz >= near) & (pz <= far)
    pz_safe = torch.where(valid, pz, torch.ones_like(pz))
    rz = 1.0 / pz_safe
    u = fx * px * rz + cx
    v = fy * py * rz + cy
    tanx = 0.5 * width / fx
    tany = 0.5 * height / fy
    ux = torch.minimum(torch.maximum(px * rz, -(cx / fx + 0.3 * tanx)), (width - cx) / fx + 0.3 * tanx)
    uy = torch.minimum(torch.maximum(py * rz, -(cy / fy + 0.3 * tany)), (height - cy) / fy + 0.3 * tany)
    zeros = torch.zeros_like(rz)
    J = torch.stack([fx * rz, zeros, -fx * ux * rz, zeros, fy * rz, -fy * uy * rz], -1)
    J = J.reshape(J.shape[:-1] + (2, 3))  # [C,N,2,3]
    Mc = torch.einsum("cij,njk->cnik", Rw, M)
    A = J @ Mc
    cov = A @ A.transpose(-1, -2)
    sa = cov[..., 0, 0] + eps2d
    sb = cov[..., 0, 1]
    sc = cov[..., 1, 1] + eps2d
    det = sa * sc - sb * sb
    valid = valid & (det > 0) & torch.isfinite(det)
    det_safe = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([sc / det_safe, -sb / det_safe, sa / det_safe], -1)
    conics = torch.where(valid[..., None], conics, torch.zeros_like(conics))
    means2d = torch.where(valid[..., None], torch.stack([u, v], -1), torch.zeros_like(conics[..., :2]))
    with torch.no_grad():
        o = opacities.to(torch.float64).expand(pz.shape)
        vis = valid & (o * 255.0 > 1.0)
        t = 2.0 * torch.log(torch.clamp(o * 255.0, min=1.0 + 1e-12))
        ex = torch.sqrt(t * sa.double())
        ey = torch.sqrt(t * sc.double())
        ud, vd = u.double(), v.double()
        x0 = torch.ceil(ud - ex - 0.5) - 1
        x1 = torch.floor(ud + ex - 0.5) + 1
        y0 = torch.ceil(vd - ey - 0.5) - 1
        y1 = torch.floor(vd + ey - 0.5) + 1
        vis = vis & ~((x1 < 0) | (y1 < 0) | (x0 > width - 1) | (y0 > height - 1))
        radii = torch.stack([torch.ceil(ex), torch.ceil(ey)], -1).clamp(max=1e9)
        radii = torch.where(vis[..., None], radii, torch.zeros_like(radii)).to(torch.int32)
        rects = torch.stack(
            [x0.clamp(min=0), x1.clamp(max=width - 1), y0.clamp(min=0), y1.clamp(max=height - 1)], -1
        )
        culled = torch.tensor([0.0, -1.0, 0.0, -1.0], dtype=rects.dtype, device=rects.device)
        rects = torch.where(vis[..., None], rects, culled).to(torch.int32)
    return means2d, conics, pz, radii, rects


def antialias(conics, opacities, eps2d=BLUR):
    """Opacities ``[C,N]`` of the antialiased mode: ``opacities [Co,N]`` times ``sqrt(det(I - eps2d conic))``
    (see ``numba_project.antialias_opacities``); differentiable in both inputs. The factor is a difference
    of nearly equal terms for sub-pixel Gaussians, so it is formed in float64 as the kernel does."""
    ca, cb, cc = conics.double().unbind(-1)
    x = 1.0 - eps2d * (ca + cc) + eps2d * eps2d * (ca * cc - cb * cb)
    pos = x > 0
    r = torch.where(pos, torch.sqrt(torch.where(pos, x, torch.ones_like(x))), torch.zeros_like(x))
    return (opacities.double() * r).to(opacities.dtype)


def composite(
    means2d, conics, opacities, colors, depths, rects, backgrounds, width, height, tile_size: int | None = 16
):
    """Front-to-back compositing; colors [Cc,N,D], opacities [Co,N]; returns
    (render_colors [C,H,W,D], render_alphas [C,H,W,1])."""
    C = means2d.shape[0]
    D = colors.shape[-1]
    dev, dt = means2d.device, means2d.dtype
    ts_x = width if tile_size is None else tile_size
    ts_y = height if tile_size is None else tile_size
    out_rows = []
    alpha_rows = []
    for c in range(C):
        vis = rects[c, :, 1] >= rects[c, :, 0]
        idx = torch.nonzero(vis).squeeze(1)
        idx = idx[torch.argsort(depths[c, idx].detach(), stable=True)]
        r = rects[c, idx]
        col_c = colors[c if colors.shape[0] > 1 else 0]
        op_c = opacities[c if opacities.shape[0] > 1 else 0]
        img = torch.zeros(height, width, D, dtype=dt, device=dev)
        acc_img = torch.zeros(height, width, dtype=dt, device=dev)
        tiles = []
        for y0 in range(0, height, ts_y):
            for x0 in range(0, width, ts_x):
                x1 = min(x0 + ts_x, width) - 1
                y1 = min(y0 + ts_y, height) - 1
                hit = (r[:, 0] <= x1) & (r[:, 1] >= x0) & (r[:, 2] <= y1) & (r[:, 3] >= y0)
                g = idx[hit]
                ys, xs = torch.meshgrid(
                    torch.arange(y0, y1 + 1, device=dev, dtype=dt),
                    torch.arange(x0, x1 + 1, device=dev, dtype=dt),
                    indexing="ij",
                )
                pix = torch.stack([xs.reshape(-1) + 0.5, ys.reshape(-1) + 0.5], -1)  # [P,2]
                if g.numel() == 0:
                    tiles.append(
                        (
                            x0,
                            x1,
                            y0,
                            y1,
                            torch.zeros(pix.shape[0], D, dtype=dt, device=dev),
                            torch.zeros(pix.shape[0], dtype=dt, device=dev),
                        )
                    )
                    continue
                d = pix[:, None, :] - means2d[c, g][None]  # [P,G,2]
                cn = conics[c, g]
                sigma = (
                    0.5 * (cn[:, 0] * d[..., 0] ** 2 + cn[:, 2] * d[..., 1] ** 2)
                    + cn[:, 1] * d[..., 0] * d[..., 1]
                )
                alpha = torch.clamp(op_c[g] * torch.exp(-sigma), max=ALPHA_MAX)
                alpha = torch.where((sigma >= 0) & (alpha >= ALPHA_MIN), alpha, torch.zeros_like(alpha))
                with torch.no_grad():
                    keep = torch.cumprod(1.0 - alpha, dim=1) >= T_MIN
                alpha = alpha * keep
                trans = torch.cumprod(1.0 - alpha, dim=1)
                t_before = torch.cat([torch.ones_like(trans[:, :1]), trans[:, :-1]], dim=1)
                w = alpha * t_before
                tiles.append((x0, x1, y0, y1, w @ col_c[g], w.sum(1)))
        rows = []
        arow = []
        for y0 in range(0, height, ts_y):
            row = [t for t in tiles if t[2] == y0]
            rows.append(torch.cat([t[4].reshape(t[3] - t[2] + 1, t[1] - t[0] + 1, D) for t in row], 1))
            arow.append(torch.cat([t[5].reshape(t[3] - t[2] + 1, t[1] - t[0] + 1) for t in row], 1))
        img = torch.cat(rows, 0)
        acc_img = torch.cat(arow, 0)
        if backgrounds is not None:
            img = img + (1.0 - acc_img)[..., None] * backgrounds[c]
        out_rows.append(img)
        alpha_rows.append(acc_img)
    colors_out, alphas_out = torch.stack(out_rows), torch.stack(alpha_rows)[..., None]
    if not colors_out.requires_grad:  # nothing visible: keep the graph connected (zero gradients)
        zero = (means2d.sum() + conics.sum() + colors.sum() + opacities.sum()) * 0.0
        colors_out, alphas_out = colors_out + zero, alphas_out + zero
    return colors_out, alphas_out


__all__ = ["project", "composite"]
