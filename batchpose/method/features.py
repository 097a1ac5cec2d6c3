"""SIFT keypoints and descriptors (optionally RootSIFT), for templates and query frames alike."""

from __future__ import annotations

import cv2
import numpy as np

from batchpose.config import FeatureConfig


def make_sift(conf: FeatureConfig) -> cv2.SIFT:
    return cv2.SIFT_create(
        nfeatures=conf.n_features,
        contrastThreshold=conf.contrast_threshold,
        edgeThreshold=conf.edge_threshold,
        sigma=conf.sigma,
    )


def detect(
    gray: np.ndarray, conf: FeatureConfig, mask: np.ndarray | None = None, sift: cv2.SIFT | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """SIFT on a grayscale image.

    Args:
        gray: (H, W) uint8 image.
        mask: optional (H, W) uint8, non-zero where keypoints may lie.

    Returns:
        xy (N, 2) float32 keypoint positions in pixels (OpenCV convention) and descriptors (N, 128) float32
        (L2-normalised SIFT scaled as OpenCV does, or RootSIFT when ``conf.root_sift``).
    """
    xy, desc, _ = detect_shapes(gray, conf, mask, sift)
    return xy, desc


def detect_shapes(
    gray: np.ndarray, conf: FeatureConfig, mask: np.ndarray | None = None, sift: cv2.SIFT | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`detect`, plus each keypoint's (N, 2) float32 ``(size_px, angle_deg)`` (OpenCV's
    ``KeyPoint.size`` and ``KeyPoint.angle``): a matched pair's size ratio and angle difference give the
    scale and in-plane rotation between the two images."""
    sift = sift or make_sift(conf)
    kps, desc = sift.detectAndCompute(gray, mask)
    if desc is None or len(kps) == 0:
        return np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32), np.zeros((0, 2), np.float32)
    xy = np.array([kp.pt for kp in kps], dtype=np.float32)
    shapes = np.array([(kp.size, kp.angle) for kp in kps], dtype=np.float32)
    desc = desc.astype(np.float32)
    if conf.root_sift:
        desc /= desc.sum(axis=1, keepdims=True) + 1e-7
        desc = np.sqrt(desc) * 512.0  # keep OpenCV-like magnitudes
    return xy, desc, shapes


def to_gray(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 RGB -> (H, W) uint8."""
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
