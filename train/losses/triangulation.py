"""Matches drawn from a dense flow and their differentiable mid-point triangulation.

TrianFlow's depth supervision (its "Pose inside training" and "Depth losses"):

* :func:`sample_matches`: the top ``top_ratio`` of the pixels of image 1 by a weight
  (``rigid * score`` for the depth losses, the score alone for the fundamental matrix),
  ``n`` of them drawn with replacement (only among those of positive weight), each
  paired with ``x + flow12(x)`` in image 2. The draw is no-grad; the image-2 points keep
  the gradient of the flow.
* :func:`midpoint_triangulate`: camera 1 at the origin, camera 2 at ``X2 = R X1 + t``
  (``(R, t) = T_cam2_cam1``); each pair of rays is closed in closed form by the mid-point
  of their common perpendicular, then filtered as the authors do: rays whose angle test
  gives ``cos < 0.001`` (parallel, or meeting behind camera 1) are dropped, then depths
  ``z <= 0.01`` in either view, then projections outside either image.
* :func:`triangulate_matches` does the same and also returns the reprojected pixels and a
  per-item ``ok`` flag with the authors' failure rules (no ray passes the angle test; fewer
  than 10 % of those have positive depth; fewer than 10 % of those project inside both
  images). The authors resample the dropped points from the kept ones; here they are
  carried with ``valid = False`` so every tensor keeps its shape (the losses average over
  the valid ones).

Pixels are ``(u, v)``; ``pts[..., 0]`` is the column. Differentiable in ``pts1``, ``pts2``,
``R``, ``t`` (the masks are not).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from trianflow_vo.errors import InputError

COS_MIN = 0.001  # the authors drop rays whose angle test is below this (about 1 arc-minute)
Z_MIN = 0.01  # the smallest depth kept, in either view
MIN_KEPT = 0.1  # an item fails when a filter keeps fewer than this fraction of its points
RAY_EPS = 1e-12  # added to norms and to the squared cross product, as the authors
PROJ_EPS = 1e-6  # smallest |z| divided by when projecting (keeps gradients finite)


def _check_points(pts1: torch.Tensor, pts2: torch.Tensor, K_inv: torch.Tensor, R: torch.Tensor,
                  t: torch.Tensor) -> None:
    if pts1.dim() != 3 or pts1.shape[-1] != 2 or pts1.shape != pts2.shape:
        raise InputError(f"pts1, pts2: expected two (N, M, 2) tensors of one shape, "
                         f"got {tuple(pts1.shape)} and {tuple(pts2.shape)}")
    n = pts1.shape[0]
    for name, x, want in (("K_inv", K_inv, (n, 3, 3)), ("R", R, (n, 3, 3)), ("t", t, (n, 3))):
        if tuple(x.shape) != want:
            raise InputError(f"{name}: expected {want}, got {tuple(x.shape)}")


def pixel_grid(h: int, w: int, dtype: torch.dtype = torch.float32, device=None) -> torch.Tensor:
    """``(2, H, W)`` pixel coordinates: channel 0 = u (column), channel 1 = v (row)."""
    v, u = torch.meshgrid(torch.arange(h, dtype=dtype, device=device),
                          torch.arange(w, dtype=dtype, device=device), indexing="ij")
    return torch.stack((u, v), dim=0)


def sample_pixels(weight: torch.Tensor, top_ratio: float = 0.2, n: int = 6000,
                  generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Flat pixel indices drawn as the authors draw matches. No gradient.

    The ``int(top_ratio * H * W)`` pixels of largest weight are kept (``torch.topk``,
    sorted); ``n`` of them are drawn uniformly with replacement, only among those whose
    weight is positive (when every kept weight is positive: among all of them).

    Args:
        weight: ``(N, 1, H, W)`` non-negative (non-finite values count as 0).
        top_ratio: share of the pixels kept, in (0, 1].
        n: how many to draw per item.
        generator: torch generator of the draw (CPU); ``None`` = torch's global one.

    Returns:
        ``idx`` ``(N, n)`` long indices into ``H * W`` (row-major) and ``ok`` ``(N,)`` bool,
        False where no kept pixel has a positive weight (``idx`` is then 0).
    """
    if weight.dim() != 4 or weight.shape[1] != 1:
        raise InputError(f"weight: expected (N, 1, H, W), got {tuple(weight.shape)}")
    if not 0.0 < top_ratio <= 1.0:
        raise InputError(f"top_ratio must be in (0, 1], got {top_ratio}")
    if int(n) != n or n < 1:
        raise InputError(f"n must be a positive integer, got {n}")
    b, _, h, w = weight.shape
    k = max(1, int(top_ratio * h * w))
    with torch.no_grad():
        wf = torch.nan_to_num(weight.detach().reshape(b, h * w).float(), nan=0.0, posinf=0.0, neginf=0.0)
        top, top_idx = torch.topk(wf, k, dim=1)  # sorted: the positive ones come first
        count = (top > 0).sum(dim=1)  # (N,)
        u = torch.rand((b, int(n)), generator=generator, dtype=torch.float64).to(weight.device)
        j = torch.floor(u * count.unsqueeze(1).to(torch.float64)).long()
        j = torch.minimum(j, (count - 1).clamp(min=0).unsqueeze(1))
        idx = torch.gather(top_idx, 1, j)
        ok = count > 0
        idx = torch.where(ok.unsqueeze(1), idx, torch.zeros_like(idx))
    return idx, ok


def sample_matches(flow12: torch.Tensor, weight: torch.Tensor, top_ratio: float = 0.2, n: int = 6000,
                   generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Matches ``x -> x + flow12(x)`` at pixels drawn by :func:`sample_pixels`.

    Args:
        flow12: ``(N, 2, H, W)`` flow from image 1 to image 2, pixels.
        weight: ``(N, 1, H, W)`` (e.g. ``rigid * score``), no gradient used.
        top_ratio, n, generator: see :func:`sample_pixels`.

    Returns:
        ``pts1`` ``(N, n, 2)`` pixel centres of image 1 (no gradient), ``pts2`` ``(N, n, 2)``
        their matches in image 2 (gradient of ``flow12`` kept), ``ok`` ``(N,)`` bool.
    """
    if flow12.dim() != 4 or flow12.shape[1] != 2:
        raise InputError(f"flow12: expected (N, 2, H, W), got {tuple(flow12.shape)}")
    b, _, h, w = flow12.shape
    if tuple(weight.shape) != (b, 1, h, w):
        raise InputError(f"weight: expected ({b}, 1, {h}, {w}), got {tuple(weight.shape)}")
    idx, ok = sample_pixels(weight, top_ratio, n, generator)
    grid = pixel_grid(h, w, flow12.dtype, flow12.device).reshape(1, 2, h * w).expand(b, 2, h * w)
    gidx = idx.unsqueeze(1).expand(b, 2, idx.shape[1])
    pts1 = torch.gather(grid, 2, gidx).transpose(1, 2)
    flow = torch.gather(flow12.reshape(b, 2, h * w), 2, gidx).transpose(1, 2)
    return pts1, pts1 + flow, ok


def _homogeneous(pts: torch.Tensor) -> torch.Tensor:
    return torch.cat((pts, torch.ones_like(pts[..., :1])), dim=-1)


def midpoint_points(pts1: torch.Tensor, pts2: torch.Tensor, K_inv: torch.Tensor, R: torch.Tensor,
                    t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mid-points of the common perpendiculars of the two rays of each match, and the angle test.

    Camera 1 is at the origin; ray 1 is ``a * d1``, ``d1 = K^-1 x1 / |K^-1 x1|``. Camera 2
    (``X2 = R X1 + t``) is at ``o2 = -R^T t`` with direction ``d2 = R^T K^-1 x2 / |.|``. With
    ``c = d1 x d2``: ``a1 = ((o2 - o1) x d2) . c / |c|^2``, ``a2 = ((o2 - o1) x d1) . c / |c|^2``
    (``+1e-12`` in the denominator), and the point is ``(a1 d1 + o2 + a2 d2) / 2``.

    The angle test (the authors'): the cosine between ``d1`` and the segment from camera 1
    to the foot of its perpendicular on ray 2; near 0 for parallel rays, negative when the
    rays meet behind camera 1.

    Args:
        pts1, pts2: ``(N, M, 2)`` pixels in images 1 and 2.
        K_inv: ``(N, 3, 3)``; R: ``(N, 3, 3)``; t: ``(N, 3)``.

    Returns:
        ``X`` ``(N, M, 3)`` points in camera-1 coordinates, ``cos`` ``(N, M)`` (no gradient).
    """
    _check_points(pts1, pts2, K_inv, R, t)
    Rt = R.transpose(1, 2)
    d1 = _homogeneous(pts1) @ K_inv.transpose(1, 2)  # (N, M, 3)
    d1 = d1 / (torch.linalg.vector_norm(d1, dim=-1, keepdim=True) + RAY_EPS)
    d2 = _homogeneous(pts2) @ K_inv.transpose(1, 2) @ R  # rows: (R^T K^-1 x2)^T
    d2 = d2 / (torch.linalg.vector_norm(d2, dim=-1, keepdim=True) + RAY_EPS)
    o2 = -(Rt @ t.unsqueeze(-1)).transpose(1, 2)  # (N, 1, 3); o1 = 0
    c = torch.cross(d1, d2, dim=-1)
    inv = 1.0 / ((c * c).sum(-1, keepdim=True) + RAY_EPS)
    base = o2.expand_as(d1)
    a1 = (torch.cross(base, d2, dim=-1) * c).sum(-1, keepdim=True) * inv
    a2 = (torch.cross(base, d1, dim=-1) * c).sum(-1, keepdim=True) * inv
    X = (a1 * d1 + o2 + a2 * d2) / 2.0
    with torch.no_grad():
        foot = o2 + ((-o2) * d2).sum(-1, keepdim=True) * d2  # foot of camera 1's perpendicular on ray 2
        cos = (d1 * foot).sum(-1) / ((torch.linalg.vector_norm(d1, dim=-1) + RAY_EPS)
                                     * (torch.linalg.vector_norm(foot, dim=-1) + RAY_EPS))
    return X, cos


def _project(K: torch.Tensor, X: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixels ``(N, M, 2)`` and depth ``(N, M)`` of camera-frame points ``X`` ``(N, M, 3)``."""
    z = X[..., 2]
    safe = torch.where(z.abs() > PROJ_EPS, z, torch.full_like(z, PROJ_EPS))
    x = X @ K.transpose(1, 2)
    return x[..., :2] / safe.unsqueeze(-1), z


@dataclass(frozen=True)
class Triangulation:
    """Triangulated matches; every field is indexed by item and match.

    Attributes:
        z1: ``(N, M)`` depth in camera 1 (scale of ``|t|``), differentiable.
        z2: ``(N, M)`` depth in camera 2.
        uv1: ``(N, M, 2)`` the point reprojected into image 1, differentiable.
        uv2: ``(N, M, 2)`` the point reprojected into image 2.
        valid: ``(N, M)`` bool, passed the angle, depth and (with a size) image filters.
        ok: ``(N,)`` bool, the item did not fail (the authors' flags).
    """

    z1: torch.Tensor
    z2: torch.Tensor
    uv1: torch.Tensor
    uv2: torch.Tensor
    valid: torch.Tensor
    ok: torch.Tensor

    def select(self, idx: torch.Tensor) -> "Triangulation":
        """The items ``idx`` (``(K,)`` long) only."""
        return Triangulation(*(getattr(self, f)[idx] for f in ("z1", "z2", "uv1", "uv2", "valid", "ok")))


def triangulate_matches(pts1: torch.Tensor, pts2: torch.Tensor, K_inv: torch.Tensor, R: torch.Tensor,
                        t: torch.Tensor, size: tuple[int, int] | None = None) -> Triangulation:
    """:func:`midpoint_points`, reprojection into both images and the authors' filters.

    Filters, in the authors' order: ``cos >= COS_MIN`` (strictly: ``cos > 0.001``), then
    ``z1 > 0.01`` and ``z2 > 0.01``, then (when ``size`` is given) ``0 < u < W`` and
    ``0 < v < H`` in both images. An item fails (``ok`` False) when no match passes the
    angle test, when fewer than 10 % of those pass the depth test, or fewer than 10 % of
    those pass the image test.

    Args:
        pts1, pts2: ``(N, M, 2)`` pixels; K_inv ``(N, 3, 3)``; R ``(N, 3, 3)``; t ``(N, 3)``.
        size: ``(H, W)`` of the images, or None to skip the image test.
    """
    X1, cos = midpoint_points(pts1, pts2, K_inv, R, t)
    K = torch.linalg.inv(K_inv)
    X2 = X1 @ R.transpose(1, 2) + t.unsqueeze(1)
    uv1, z1 = _project(K, X1)
    uv2, z2 = _project(K, X2)
    with torch.no_grad():
        ang = cos > COS_MIN
        pos = ang & (z1 > Z_MIN) & (z2 > Z_MIN)
        valid = pos
        if size is not None:
            h, w = size
            lim = torch.tensor([w, h], dtype=uv1.dtype, device=uv1.device)
            inside = ((uv1 > 0) & (uv1 < lim) & (uv2 > 0) & (uv2 < lim)).all(dim=-1)
            valid = pos & inside
        n_ang = ang.sum(1)
        n_pos = pos.sum(1)
        n_val = valid.sum(1)
        ok = (n_ang > 0) & (n_pos >= MIN_KEPT * n_ang) & (n_val >= MIN_KEPT * n_pos) & (n_val > 0)
        ok = ok & torch.isfinite(X1.detach()).all(dim=-1).any(dim=1)
    return Triangulation(z1=z1, z2=z2, uv1=uv1, uv2=uv2, valid=valid, ok=ok)


def midpoint_triangulate(pts1: torch.Tensor, pts2: torch.Tensor, K_inv: torch.Tensor, R: torch.Tensor,
                         t: torch.Tensor, size: tuple[int, int] | None = None
                         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Differentiable closed-form mid-point triangulation with the authors' filters.

    Args:
        pts1, pts2: ``(N, M, 2)`` matched pixels of images 1 and 2.
        K_inv: ``(N, 3, 3)`` inverse intrinsics (one camera for both images).
        R: ``(N, 3, 3)``, t: ``(N, 3)``: ``X2 = R X1 + t`` (``T_cam2_cam1``); depths come out
            in the scale of ``|t|``.
        size: ``(H, W)``: also drop points projecting outside either image.

    Returns:
        ``z1`` ``(N, M)``, ``z2`` ``(N, M)`` depths in cameras 1 and 2, ``valid`` ``(N, M)``
        bool (see :func:`triangulate_matches`).
    """
    tri = triangulate_matches(pts1, pts2, K_inv, R, t, size)
    return tri.z1, tri.z2, tri.valid
