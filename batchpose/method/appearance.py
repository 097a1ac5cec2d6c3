"""How alike a rendered object and the frame look: colour bins and texture / gradient correlation."""

from __future__ import annotations

import cv2
import numpy as np

#: Hue bins, saturation bins (for saturated pixels) and grey-level bins (for the others).
N_HUE, N_SAT, N_GREY = 12, 3, 4


#: Saturation below which a pixel's hue is noise and its grey level is used instead.
MIN_SATURATION = 48


N_BINS = N_HUE * N_SAT + N_GREY


def colour_bins(rgb: np.ndarray) -> np.ndarray:
    """Each pixel's colour bin (see :data:`N_BINS`)."""
    hsv = cv2.cvtColor(rgb, cv2.COLOR_RGB2HSV).astype(np.int32)
    h = (hsv[..., 0] * N_HUE) // 180
    s = ((hsv[..., 1] - MIN_SATURATION).clip(0) * N_SAT) // (256 - MIN_SATURATION)
    v = (hsv[..., 2] * N_GREY) // 256
    return np.where(hsv[..., 1] >= MIN_SATURATION, h * N_SAT + s, N_HUE * N_SAT + v)


def _correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Normalised cross-correlation of two (N, 3) colour samples (each channel about its mean)."""
    a = a.astype(np.float64) - a.mean(axis=0)
    b = b.astype(np.float64) - b.mean(axis=0)
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum() + 1e-9))


def texture_match(frame_lab: np.ndarray, rendered_rgb: np.ndarray) -> float:
    """How well a rendered mesh's colours line up with the frame's: :func:`_correlation` of (N, 3) samples in
    Lab, the frame's already converted, the render's RGB."""
    return _correlation(frame_lab, cv2.cvtColor(rendered_rgb[None], cv2.COLOR_RGB2LAB)[0])


def gradient_match(frame_gray: np.ndarray, rendered_gray: np.ndarray, px: np.ndarray) -> float:
    """How well a render's edges line up with the frame's over the pixels ``px`` (bool mask): the summed
    |dot product| of their Sobel gradients over the product of the gradients' norms, in [0, 1]. Blind to
    colour and to the sign of an edge (the object lighter or darker than what is behind it)."""
    out = []
    for img in (frame_gray, rendered_gray):
        g = img.astype(np.float32)
        out.append((cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3)[px], cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)[px]))
    (fx, fy), (rx, ry) = out
    dot = float(np.abs(fx * rx + fy * ry).sum())
    return dot / float(np.sqrt((fx * fx + fy * fy).sum() * (rx * rx + ry * ry).sum()) + 1e-9)
