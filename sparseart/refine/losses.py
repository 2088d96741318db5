"""Losses of the refinement: photometric L1 + D-SSIM, depth and silhouette terms, and the
weighted Chamfer distance between Gaussian centres.

Images are (H, W, 3) tensors in [0, 1]; depth (H, W) camera z in frame units (0 = invalid);
``weight`` (H, W) in [0, 1] selects the pixels that count (0 for pixels of parts not modelled).
"""
from __future__ import annotations

import numpy as np

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_C1 = 0.01 ** 2
SSIM_C2 = 0.03 ** 2


def _gaussian_window(dtype):
    import torch

    x = torch.arange(SSIM_WINDOW, dtype=dtype) - (SSIM_WINDOW - 1) / 2
    g = torch.exp(-x * x / (2 * SSIM_SIGMA ** 2))
    g = g / g.sum()
    return (g[:, None] * g[None, :]).expand(3, 1, SSIM_WINDOW, SSIM_WINDOW).contiguous()


def ssim_map(image, target):
    """(H, W) per-pixel SSIM (11x11 Gaussian window, sigma 1.5, as 3DGS) averaged over colour.
    O(H W 121)."""
    import torch.nn.functional as F

    window = _gaussian_window(image.dtype)
    x = image.permute(2, 0, 1)[None]
    y = target.permute(2, 0, 1)[None]
    pad = SSIM_WINDOW // 2

    def blur(z):
        return F.conv2d(F.pad(z, (pad, pad, pad, pad), mode="replicate"), window, groups=3)

    mu_x, mu_y = blur(x), blur(y)
    sigma_x = blur(x * x) - mu_x ** 2
    sigma_y = blur(y * y) - mu_y ** 2
    sigma_xy = blur(x * y) - mu_x * mu_y
    ssim = ((2 * mu_x * mu_y + SSIM_C1) * (2 * sigma_xy + SSIM_C2)) / (
        (mu_x ** 2 + mu_y ** 2 + SSIM_C1) * (sigma_x + sigma_y + SSIM_C2))
    return ssim[0].mean(dim=0)


def photometric_loss(image, target, weight, ssim_weight: float = 0.2):
    """(1 - lambda) weighted-mean L1 + lambda weighted-mean D-SSIM, D-SSIM = (1 - SSIM) / 2."""
    total = weight.sum().clamp_min(1.0)
    l1 = ((image - target).abs().mean(dim=-1) * weight).sum() / total
    if ssim_weight <= 0:
        return l1
    dssim = (((1.0 - ssim_map(image, target)) / 2.0) * weight).sum() / total
    return (1.0 - ssim_weight) * l1 + ssim_weight * dssim


def depth_loss(rendered_depth, rendered_alpha, target_depth, weight, scale: float):
    """Depth and silhouette term: weighted-mean |D - z| / scale over pixels with a valid target
    depth (D is alpha-weighted, so it also pulls alpha to 1 there) plus weighted-mean
    |alpha - [z > 0]| over all pixels (empty background stays empty)."""
    valid = (target_depth > 0).to(rendered_depth.dtype) * weight
    depth_term = ((rendered_depth - target_depth).abs() * valid).sum() / valid.sum().clamp_min(1.0) / scale
    silhouette = ((rendered_alpha - (target_depth > 0).to(rendered_alpha.dtype)).abs() * weight).sum() \
        / weight.sum().clamp_min(1.0)
    return depth_term + silhouette


def psnr(image: np.ndarray, target: np.ndarray) -> float:
    """PSNR in dB of two (H, W, 3) images in [0, 1]; inf when identical."""
    mse = float(np.mean((np.asarray(image, np.float64) - np.asarray(target, np.float64)) ** 2))
    return float("inf") if mse <= 0 else float(-10.0 * np.log10(mse))


def weighted_chamfer(source, target, source_weight, target_weight, cap: float, both: bool = True):
    """Weighted Chamfer distance between two sets of centres.

    source (N, 3), target (M, 3) tensors; source_weight (N,), target_weight (M,) non-negative
    (normalised here). Nearest neighbours are found with a scipy KD-tree (no gradient: the
    matching is piecewise constant), then the matched pairs' distances are gathered
    differentiably; each distance is capped at ``cap`` (frame units) so unmatched regions (parts
    seen in one state only) cost a constant instead of dominating.
    Returns sum_i w_i min(|s_i - t_nn(i)|, cap) / sum w (+ the same from target to source).
    O((N + M) log(N + M)).
    """
    import torch
    from scipy.spatial import cKDTree

    if len(source) == 0 or len(target) == 0:
        return torch.zeros((), dtype=source.dtype)

    def one_way(a, b, wa):
        _, nearest = cKDTree(b.detach().double().numpy()).query(a.detach().double().numpy(), k=1)
        dist = ((a - b[torch.as_tensor(nearest)]) ** 2).sum(-1).clamp_min(1e-18).sqrt()
        return (wa * dist.clamp(max=cap)).sum() / wa.sum().clamp_min(1e-12)

    loss = one_way(source, target, source_weight)
    if both:
        loss = loss + one_way(target, source, target_weight)
    return loss
