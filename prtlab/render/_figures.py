"""Figure helpers in the style of the papers' comparisons (matplotlib).

Side-by-side panels, false-colour difference images with a colour bar, and
per-vertex agreement scatter plots with error bars. Each function returns the
matplotlib ``Figure`` (and draws into ``ax`` when given); nothing is shown.
"""

from __future__ import annotations

import numpy as np

from ._tonemap import tonemap

__all__ = ["comparison_figure", "difference_figure", "agreement_plot", "luminance"]


def luminance(img) -> np.ndarray:
    """Rec. 709 luminance ``0.2126 R + 0.7152 G + 0.0722 B`` of (..., 3) linear RGB."""
    img = np.asarray(img, dtype=np.float64)
    if img.ndim == 0 or img.shape[-1] != 3:
        raise ValueError(f"img must be a (..., 3) RGB array, got shape {img.shape}")
    return img @ np.array([0.2126, 0.7152, 0.0722])


def _plt():
    import matplotlib.pyplot as plt

    return plt


def comparison_figure(images, titles=None, *, exposure: float = 0.0, curve: str = "clip",
                      panel_size: float = 3.2, suptitle: str | None = None):
    """Linear images side by side, tone mapped alike, with a title over each.

    Parameters
    ----------
    images : sequence of (h, w, 3) float
        Linear RGB.
    titles : sequence of str, optional
    exposure : float
        Stops, the same for every panel.
    curve : {"clip", "reinhard", "aces"}
    panel_size : float
        Panel height in inches.
    suptitle : str, optional

    Returns
    -------
    matplotlib.figure.Figure
    """
    images = [np.asarray(im, dtype=np.float64) for im in images]
    if not images:
        raise ValueError("images is empty: give at least one (h, w, 3) image")
    for k, im in enumerate(images):
        if im.ndim != 3 or im.shape[-1] != 3:
            raise ValueError(f"images[{k}] must be (h, w, 3), got shape {im.shape}")
    titles = list(titles) if titles is not None else [""] * len(images)
    if len(titles) != len(images):
        raise ValueError(f"titles has {len(titles)} entries for {len(images)} images; give one per image")
    plt = _plt()
    aspect = images[0].shape[1] / images[0].shape[0]
    fig, axes = plt.subplots(1, len(images), figsize=(panel_size * aspect * len(images), panel_size + 0.4),
                             squeeze=False)
    for ax, im, title in zip(axes[0], images, titles):
        ax.imshow(tonemap(im, exposure=exposure, curve=curve), interpolation="nearest")
        ax.set_title(title, fontsize=10)
        ax.set_axis_off()
    if suptitle:
        fig.suptitle(suptitle)
    fig.tight_layout()
    return fig


def difference_figure(test, reference, *, mode: str = "relative", vmax: float | None = None,
                      cmap: str = "magma", title: str | None = None, ax=None, eps: float = 1e-3):
    """False-colour difference of two linear images, with a colour bar.

    Parameters
    ----------
    test, reference : (h, w, 3) float
    mode : {"relative", "absolute", "signed"}
        ``relative``: ``|L(test) - L(ref)| / (L(ref) + eps)`` on luminance;
        ``absolute``: ``|L(test) - L(ref)|``; ``signed``: ``L(test) - L(ref)``
        (diverging colour map centred on zero).
    vmax : float, optional
        Colour-scale maximum (default: the 99th percentile).
    cmap : str
    title : str, optional
    ax : matplotlib Axes, optional
    eps : float
        Regulariser of the relative difference, relative to the mean reference luminance.

    Returns
    -------
    matplotlib.figure.Figure
    """
    a = np.asarray(test, dtype=np.float64)
    b = np.asarray(reference, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 3 or a.shape[-1] != 3:
        raise ValueError(f"test and reference must be (h, w, 3) of the same shape, got {a.shape} and {b.shape}")
    la, lb = luminance(a), luminance(b)
    if mode == "relative":
        diff = np.abs(la - lb) / (lb + eps * max(float(np.mean(lb)), 1e-12))
        label = "relative difference"
    elif mode == "absolute":
        diff = np.abs(la - lb)
        label = "absolute difference (luminance)"
    elif mode == "signed":
        diff = la - lb
        label = "test - reference (luminance)"
        cmap = "RdBu_r" if cmap == "magma" else cmap
    else:
        raise ValueError(f"mode must be 'relative', 'absolute' or 'signed', got {mode!r}")
    finite = diff[np.isfinite(diff)]
    if vmax is None:
        vmax = float(np.percentile(np.abs(finite), 99)) if finite.size else 1.0
        vmax = vmax if vmax > 0 else 1.0
    plt = _plt()
    if ax is None:
        fig, ax = plt.subplots(figsize=(3.2 * a.shape[1] / a.shape[0] + 0.8, 3.6))
    else:
        fig = ax.figure
    vmin = -vmax if mode == "signed" else 0.0
    im = ax.imshow(diff, cmap=cmap, vmin=vmin, vmax=vmax, interpolation="nearest")
    fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04, label=label)
    ax.set_title(title or label, fontsize=10)
    ax.set_axis_off()
    return fig


def agreement_plot(reference, estimate, reference_err=None, estimate_err=None, *, ax=None,
                   xlabel: str = "reference", ylabel: str = "estimate", title: str | None = None,
                   channel: str = "luminance", max_points: int = 3000, seed: int = 0):
    """Per-vertex scatter of two estimates with error bars and the line ``y = x``.

    Parameters
    ----------
    reference, estimate : (n, 3) or (n,) float
        Per-vertex radiance of the two methods.
    reference_err, estimate_err : same shape, optional
        Standard errors (drawn as +-1 sigma bars).
    ax : matplotlib Axes, optional
    xlabel, ylabel, title : str
    channel : {"luminance", "r", "g", "b"}
        What to plot for RGB input. The luminance error bar is the weighted sum
        of the channel errors, exact for fully correlated channels and an upper
        bound otherwise.
    max_points : int
        Random subset drawn when there are more vertices.
    seed : int

    Returns
    -------
    matplotlib.figure.Figure
    """
    x, y = np.asarray(reference, dtype=np.float64), np.asarray(estimate, dtype=np.float64)
    if x.shape != y.shape:
        raise ValueError(f"reference and estimate must have the same shape, got {x.shape} and {y.shape}")
    xe = None if reference_err is None else np.asarray(reference_err, dtype=np.float64)
    ye = None if estimate_err is None else np.asarray(estimate_err, dtype=np.float64)
    for name, e in (("reference_err", xe), ("estimate_err", ye)):
        if e is not None and e.shape != x.shape:
            raise ValueError(f"{name} must have the shape of the values {x.shape}, got {e.shape}")

    def pick(v):
        if v is None or v.ndim == 1:
            return v
        if channel == "luminance":
            return luminance(v)
        if channel in ("r", "g", "b"):
            return v[..., "rgb".index(channel)]
        raise ValueError(f"channel must be 'luminance', 'r', 'g' or 'b', got {channel!r}")

    x, y, xe, ye = pick(x), pick(y), pick(xe), pick(ye)
    if len(x) > max_points:
        keep = np.random.default_rng(seed).choice(len(x), max_points, replace=False)
        x, y = x[keep], y[keep]
        xe = None if xe is None else xe[keep]
        ye = None if ye is None else ye[keep]
    plt = _plt()
    if ax is None:
        fig, ax = plt.subplots(figsize=(4.2, 4.0))
    else:
        fig = ax.figure
    ax.errorbar(x, y, xerr=xe, yerr=ye, fmt="o", ms=2.5, lw=0.6, alpha=0.7, capsize=0)
    lo = float(min(x.min(), y.min(), 0.0)) if len(x) else 0.0
    hi = float(max(x.max(), y.max())) if len(x) else 1.0
    ax.plot([lo, hi], [lo, hi], "k--", lw=0.8, label="y = x")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title, fontsize=10)
    ax.legend(loc="upper left", fontsize=8)
    return fig
