"""Image-quality metrics (NHA / PointAvatar tables): L1, PSNR, SSIM, MS-SSIM, masked or not;
LPIPS and FID/KID only when their pretrained weights are present ("n/a" otherwise).

Images are float tensors in [0, 1], shape (B, H, W, C); masks (B, H, W) bool or float in
[0, 1]. Every function returns one value per image, shape (B,).
"""

from __future__ import annotations

import numba
import numpy as np
import torch
import torch.nn.functional as F

from headforge.errors import HeadforgeError

MS_SSIM_WEIGHTS = (0.0448, 0.2856, 0.3001, 0.2363, 0.1333)  # Wang et al. 2003


def _check(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None) -> None:
    if pred.shape != gt.shape or pred.ndim != 4:
        raise HeadforgeError(f"images must both be (B, H, W, C) of one shape, got {tuple(pred.shape)} and {tuple(gt.shape)}")
    if mask is not None:
        if mask.shape != pred.shape[:3]:
            raise HeadforgeError(f"mask must be (B, H, W) = {tuple(pred.shape[:3])}, got {tuple(mask.shape)}")
        if not (mask > 0).flatten(1).any(1).all():
            raise HeadforgeError("a mask is empty: no pixels to evaluate")


def _weights(mask: torch.Tensor | None, like: torch.Tensor) -> torch.Tensor:
    return torch.ones(like.shape[:3], dtype=like.dtype, device=like.device) if mask is None else mask.to(like.dtype)


def l1(pred, gt, mask=None) -> torch.Tensor:
    """Mean absolute error over (masked) pixels and channels."""
    _check(pred, gt, mask)
    w = _weights(mask, pred)
    return ((pred - gt).abs().mean(-1) * w).flatten(1).sum(1) / w.flatten(1).sum(1)


def mse(pred, gt, mask=None) -> torch.Tensor:
    _check(pred, gt, mask)
    w = _weights(mask, pred)
    return ((pred - gt).pow(2).mean(-1) * w).flatten(1).sum(1) / w.flatten(1).sum(1)


def psnr(pred, gt, mask=None) -> torch.Tensor:
    """10 log10(1 / MSE), images in [0, 1]; inf for identical images."""
    return 10 * torch.log10(1.0 / mse(pred, gt, mask))


def _gaussian(size: int, sigma: float, dtype, device) -> torch.Tensor:
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-x ** 2 / (2 * sigma ** 2))
    return g / g.sum()


def _blur(x: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Separable 'valid' Gaussian filtering of (N, C, H, W)."""
    C = x.shape[1]
    x = F.conv2d(x, g.view(1, 1, 1, -1).expand(C, 1, 1, -1), groups=C)
    return F.conv2d(x, g.view(1, 1, -1, 1).expand(C, 1, -1, 1), groups=C)


def _ssim_maps(pred: torch.Tensor, gt: torch.Tensor, win: int = 11, sigma: float = 1.5):
    """SSIM and contrast-structure maps (N, C, h, w) on the valid region (Wang et al. 2004)."""
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    g = _gaussian(win, sigma, pred.dtype, pred.device)
    mu_x, mu_y = _blur(pred, g), _blur(gt, g)
    sxx = _blur(pred * pred, g) - mu_x ** 2
    syy = _blur(gt * gt, g) - mu_y ** 2
    sxy = _blur(pred * gt, g) - mu_x * mu_y
    cs = (2 * sxy + c2) / (sxx + syy + c2)
    return (2 * mu_x * mu_y + c1) / (mu_x ** 2 + mu_y ** 2 + c1) * cs, cs


def _crop_mask(mask: torch.Tensor, win: int) -> torch.Tensor:
    """The mask on the valid region of a win x win filter: (B, h, w)."""
    r = win // 2
    return mask[:, r: mask.shape[1] - r, r: mask.shape[2] - r]


def ssim(pred, gt, mask=None, win: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Structural similarity, Gaussian window 11/1.5, data range 1, averaged over channels and
    over the (masked) valid region -- scikit-image's gaussian_weights=True convention."""
    _check(pred, gt, mask)
    if min(pred.shape[1:3]) < win:
        raise HeadforgeError(f"SSIM needs images of at least {win}x{win} pixels")
    s, _ = _ssim_maps(pred.permute(0, 3, 1, 2), gt.permute(0, 3, 1, 2), win, sigma)
    s = s.mean(1)
    w = torch.ones_like(s) if mask is None else _crop_mask(mask.to(s.dtype), win)
    return (s * w).flatten(1).sum(1) / w.flatten(1).sum(1).clamp(min=1e-12)


def ms_ssim(pred, gt, mask=None, win: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Multi-scale SSIM over 5 scales (average pooling by 2 between scales, odd sizes
    zero-padded); the mask is pooled with the images and used as weights at every scale."""
    _check(pred, gt, mask)
    need = (win - 1) * 2 ** (len(MS_SSIM_WEIGHTS) - 1)
    if min(pred.shape[1:3]) <= need:
        raise HeadforgeError(f"MS-SSIM needs images larger than {need}x{need} pixels")
    x, y = pred.permute(0, 3, 1, 2), gt.permute(0, 3, 1, 2)
    m = (torch.ones(pred.shape[:3], dtype=pred.dtype, device=pred.device) if mask is None else mask.to(pred.dtype))[:, None]
    values = []
    for level, _ in enumerate(MS_SSIM_WEIGHTS):
        s, cs = _ssim_maps(x, y, win, sigma)
        w = _crop_mask(m[:, 0], win)[:, None]
        avg = lambda t: (t * w).flatten(1).sum(1) / (w.flatten(1).sum(1) * t.shape[1]).clamp(min=1e-12)  # noqa: E731
        values.append(avg(s if level == len(MS_SSIM_WEIGHTS) - 1 else cs).clamp(min=0))
        if level < len(MS_SSIM_WEIGHTS) - 1:
            pad = (x.shape[2] % 2, x.shape[3] % 2)  # odd sizes: zero-pad, as the reference implementations
            x, y, m = (F.avg_pool2d(t, 2, padding=pad) for t in (x, y, m))
    weights = torch.tensor(MS_SSIM_WEIGHTS, dtype=pred.dtype, device=pred.device)
    return torch.prod(torch.stack(values, 0) ** weights[:, None], dim=0)


def lpips(pred, gt):
    """LPIPS (AlexNet) when the ``lpips`` package and its backbone weights are available
    locally; otherwise None (reported as "n/a"). Never downloads."""
    try:
        import lpips as lpips_pkg  # noqa: F401
    except ImportError:
        return None
    try:
        model = lpips_pkg.LPIPS(net="alex", verbose=False, pretrained=True)
    except Exception:  # weights missing and no network: n/a
        return None
    with torch.no_grad():
        return model(pred.permute(0, 3, 1, 2) * 2 - 1, gt.permute(0, 3, 1, 2) * 2 - 1).flatten()


def fid_from_features(a: torch.Tensor, b: torch.Tensor) -> float:
    """Frechet distance between Gaussians fitted to feature sets (N, D) and (M, D)."""
    import numpy as np
    from scipy import linalg

    a, b = a.double().cpu().numpy(), b.double().cpu().numpy()
    mu1, mu2 = a.mean(0), b.mean(0)
    s1, s2 = np.cov(a, rowvar=False), np.cov(b, rowvar=False)
    covmean, _ = linalg.sqrtm(s1 @ s2, disp=False)
    covmean = covmean.real
    return float(((mu1 - mu2) ** 2).sum() + np.trace(s1 + s2 - 2 * covmean))


def kid_from_features(a: torch.Tensor, b: torch.Tensor) -> float:
    """Kernel inception distance: unbiased MMD^2 with the cubic polynomial kernel."""
    a, b = a.double(), b.double()
    d = a.shape[1]
    k = lambda x, y: (x @ y.T / d + 1) ** 3  # noqa: E731
    n, m = len(a), len(b)
    kaa, kbb, kab = k(a, a), k(b, b), k(a, b)
    return float((kaa.sum() - kaa.diag().sum()) / (n * (n - 1)) + (kbb.sum() - kbb.diag().sum()) / (m * (m - 1))
                 - 2 * kab.mean())


# ---- CPBD: cumulative probability of blur detection (Narvekar & Karam, 2011) ----------------
def _sobel_edges(gray: np.ndarray) -> np.ndarray:
    """Vertical edges as Octave's edge(I, 'sobel') finds them: squared response of the
    normalised x-derivative Sobel filter, thresholded at 2 sqrt(mean), thinned to pixels that
    are strict local maxima horizontally or vertically."""
    from scipy.ndimage import convolve

    kernel = np.array([[1.0, 0, -1], [2, 0, -2], [1, 0, -1]]) / 8.0
    strength = convolve(gray, kernel) ** 2
    strength[strength <= 2 * np.sqrt(strength.mean())] = 0
    pad = np.pad(strength, 1)
    centre = pad[1:-1, 1:-1]
    horizontal = (centre > pad[1:-1, :-2]) & (centre > pad[1:-1, 2:])
    vertical = (centre > pad[:-2, 1:-1]) & (centre > pad[2:, 1:-1])
    return horizontal | vertical


@numba.njit(cache=True)
def _edge_widths(gray, edges, direction):
    """Marziliano widths along rows: from the edge pixel, walk to the intensity extrema on
    both sides (direction +1: intensity rises to the right, -1: falls)."""
    h, w = gray.shape
    out = np.zeros((h, w))
    for r in range(1, h - 1):
        for c in range(1, w - 1):
            if not edges[r, c] or direction[r, c] == 0:
                continue
            rise = direction[r, c]
            left = 0
            while c - 2 - left >= 0 and rise * (gray[r, c - 1 - left] - gray[r, c - 2 - left]) > 0:
                left += 1
            right = 0
            while c + 2 + right < w and rise * (gray[r, c + 2 + right] - gray[r, c + 1 + right]) > 0:
                right += 1
            out[r, c] = left + right + 2
    return out


def cpbd(image) -> float:
    """No-reference sharpness in [0, 1] (higher is sharper): NHA's CPBD column.

    image: (H, W, 3) or (H, W) in [0, 1]. Edge widths (Marziliano) at vertical edges; in each
    64x64 block with more than 0.2 % Canny edge pixels, the just-noticeable-blur width is 5 px
    (block contrast <= 50/255) or 3 px; an edge is seen as blurred with probability
    1 - exp(-(w / w_JNB)^3.6), and CPBD is the share of edges with probability <= 63 %
    (probabilities bucketed to whole percents, as in the reference implementation).
    """
    from skimage.feature import canny

    if isinstance(image, torch.Tensor):
        image = image.detach().cpu().numpy()
    image = np.asarray(image, np.float64)
    gray = (image @ np.array([0.299, 0.587, 0.114]) if image.ndim == 3 else image) * 255.0
    blocks_edges = canny(gray)
    gy, gx = np.gradient(gray)
    quantised = 45 * np.round(np.degrees(np.arctan2(gy, gx)) / 45)
    direction = np.where(quantised == 0, 1, np.where(np.abs(quantised) == 180, -1, 0)).astype(np.int64)
    direction[gx == 0] = 0
    widths = _edge_widths(gray, _sobel_edges(gray).astype(np.uint8), direction)
    histogram = np.zeros(101)
    for r0 in range(0, gray.shape[0] - 63, 64):
        for c0 in range(0, gray.shape[1] - 63, 64):
            if blocks_edges[r0:r0 + 64, c0:c0 + 64].sum() <= 0.002 * 64 * 64:
                continue
            block = gray[r0:r0 + 64, c0:c0 + 64]
            w_jnb = 5.0 if int(block.max() - block.min()) <= 50 else 3.0
            bw = widths[r0:r0 + 64, c0:c0 + 64]
            bw = bw[bw != 0]
            prob = 1 - np.exp(-np.abs(bw / w_jnb) ** 3.6)
            np.add.at(histogram, np.round(prob * 100).astype(int), 1)
    total = histogram.sum()
    return float(histogram[:64].sum() / total) if total else float("nan")
