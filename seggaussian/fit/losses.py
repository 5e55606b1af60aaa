"""Image losses and metrics of 3DGS fitting: L1, SSIM (Gaussian window 11, sigma 1.5), PSNR.

Images are float tensors ``[H, W, C]`` (or ``[B, H, W, C]``) with values in [0, 1]. SSIM follows the
3DGS reference ``utils/loss_utils.py``: a normalized 11x11 Gaussian window (sigma 1.5) applied per
channel with zero padding of 5 pixels ("same" size), constants C1 = 0.01^2, C2 = 0.03^2, mean over all
pixels and channels. ``ssim`` uses the separable window (two 1D convolutions); ``ssim_reference``
applies the full 2D window and is kept as the slow, obviously-correct reference for the tests.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

#: SSIM window edge in pixels (3DGS: 11).
SSIM_WINDOW_SIZE = 11
#: Standard deviation of the SSIM Gaussian window in pixels (3DGS: 1.5).
SSIM_SIGMA = 1.5
#: SSIM stabilizer of the luminance term, (0.01 * L)^2 for a dynamic range L = 1.
SSIM_C1 = 0.01**2
#: SSIM stabilizer of the contrast-structure term, (0.03 * L)^2 for L = 1.
SSIM_C2 = 0.03**2
#: Mean squared error floor in PSNR: caps a perfect match at 100 dB instead of +inf.
PSNR_MSE_FLOOR = 1e-10


def l1_loss(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean absolute difference (scalar)."""
    return (image - target).abs().mean()


def psnr(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB for a peak value of 1 (scalar)."""
    mse = ((image - target) ** 2).mean()
    return -10.0 * torch.log10(mse.clamp_min(PSNR_MSE_FLOOR))


def gaussian_window_1d(size: int = SSIM_WINDOW_SIZE, sigma: float = SSIM_SIGMA,
                       dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """``[size]`` normalized Gaussian weights centred on the middle tap."""
    centre = size // 2
    values = [math.exp(-((i - centre) ** 2) / (2.0 * sigma**2)) for i in range(size)]
    total = sum(values)
    return torch.tensor([v / total for v in values], dtype=dtype)


def _as_nchw(image: torch.Tensor) -> torch.Tensor:
    if image.dim() == 3:
        image = image.unsqueeze(0)
    if image.dim() != 4:
        raise ValueError(f"SSIM expects an image [H, W, C] or [B, H, W, C], got shape {tuple(image.shape)}")
    return image.permute(0, 3, 1, 2)


def _ssim_from_moments(mu1, mu2, e11, e22, e12) -> torch.Tensor:
    mu1_sq, mu2_sq, mu12 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    sigma1_sq, sigma2_sq, sigma12 = e11 - mu1_sq, e22 - mu2_sq, e12 - mu12
    numerator = (2.0 * mu12 + SSIM_C1) * (2.0 * sigma12 + SSIM_C2)
    denominator = (mu1_sq + mu2_sq + SSIM_C1) * (sigma1_sq + sigma2_sq + SSIM_C2)
    return (numerator / denominator).mean()


def ssim(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean SSIM (scalar), separable Gaussian window; differentiable in both inputs."""
    if image.shape != target.shape:
        raise ValueError(f"SSIM: image shape {tuple(image.shape)} differs from target {tuple(target.shape)}")
    x, y = _as_nchw(image), _as_nchw(target)
    channels = x.shape[1]
    w = gaussian_window_1d(dtype=x.dtype).to(x.device)
    pad = SSIM_WINDOW_SIZE // 2
    kernel_h = w.view(1, 1, 1, -1).expand(channels, 1, 1, SSIM_WINDOW_SIZE).contiguous()
    kernel_v = w.view(1, 1, -1, 1).expand(channels, 1, SSIM_WINDOW_SIZE, 1).contiguous()
    # the five moments are filtered in one batched call: [5B, C, H, W]
    stack = torch.cat([x, y, x * x, y * y, x * y], dim=0)
    filtered = F.conv2d(stack, kernel_h, padding=(0, pad), groups=channels)
    filtered = F.conv2d(filtered, kernel_v, padding=(pad, 0), groups=channels)
    mu1, mu2, e11, e22, e12 = filtered.chunk(5, dim=0)
    return _ssim_from_moments(mu1, mu2, e11, e22, e12)


def ssim_reference(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean SSIM with the full 2D window, one channel at a time (slow reference of ``ssim``)."""
    x, y = _as_nchw(image), _as_nchw(target)
    w = gaussian_window_1d(dtype=x.dtype).to(x.device)
    window = torch.outer(w, w).view(1, 1, SSIM_WINDOW_SIZE, SSIM_WINDOW_SIZE)
    pad = SSIM_WINDOW_SIZE // 2
    maps = []
    for c in range(x.shape[1]):
        a, b = x[:, c : c + 1], y[:, c : c + 1]
        mu1 = F.conv2d(a, window, padding=pad)
        mu2 = F.conv2d(b, window, padding=pad)
        e11 = F.conv2d(a * a, window, padding=pad)
        e22 = F.conv2d(b * b, window, padding=pad)
        e12 = F.conv2d(a * b, window, padding=pad)
        mu1_sq, mu2_sq, mu12 = mu1 * mu1, mu2 * mu2, mu1 * mu2
        s = ((2 * mu12 + SSIM_C1) * (2 * (e12 - mu12) + SSIM_C2)) / (
            (mu1_sq + mu2_sq + SSIM_C1) * ((e11 - mu1_sq) + (e22 - mu2_sq) + SSIM_C2))
        maps.append(s)
    return torch.cat(maps, dim=1).mean()


def fitting_loss(image: torch.Tensor, target: torch.Tensor, lambda_dssim: float) -> torch.Tensor:
    """3DGS photometric loss ``(1 - lambda) * L1 + lambda * (1 - SSIM)`` (scalar)."""
    loss = (1.0 - lambda_dssim) * l1_loss(image, target)
    if lambda_dssim > 0.0:
        loss = loss + lambda_dssim * (1.0 - ssim(image, target))
    return loss


def depth_loss(depth: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean relative depth error ``|D - D*| / D*`` over the pixels where the target depth is positive
    (and ``mask`` is True): ``depth`` is the rendered expected depth ``[H, W]``, ``target`` the reference
    depth ``[H, W]`` (0 = unknown, e.g. a ray that missed the mesh). Scalar; 0 when no pixel counts."""
    if depth.shape != target.shape:
        raise ValueError(f"depth_loss: depth shape {tuple(depth.shape)} differs from target {tuple(target.shape)}")
    known = target > 0.0
    if mask is not None:
        known = known & mask
    count = known.sum()
    if int(count) == 0:
        return depth.sum() * 0.0
    safe = torch.where(known, target, torch.ones_like(target))
    err = torch.where(known, (depth - target).abs() / safe, torch.zeros_like(depth))
    return err.sum() / count
