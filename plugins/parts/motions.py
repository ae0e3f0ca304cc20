"""Rigid-motion algebra: twists and screw motions."""

from __future__ import annotations

import cv2
import numpy as np


def _V(w: np.ndarray) -> np.ndarray:
    """The matrix (3, 3) by which exp of the twist (w, v) moves the origin: V(w) v."""
    theta = float(np.sqrt(w @ w))
    K = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])  # K v = w x v
    if theta < 1e-9:
        return np.eye(3) + K / 2
    return np.eye(3) + (1 - np.cos(theta)) / theta**2 * K + (theta - np.sin(theta)) / theta**3 * (K @ K)


def _twist_log(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The twist (w, v), radians and metres, with exp(w, v) the rigid motion T (4, 4)."""
    w = cv2.Rodrigues(np.ascontiguousarray(T[:3, :3]))[0].ravel()  # as scipy's Rotation, 20 times faster
    return w, np.linalg.solve(_V(w), T[:3, 3])


def _screw(T: np.ndarray, s: float) -> np.ndarray:
    """The rigid motion T (4, 4) taken ``s`` times along its screw: ``exp(s log T)``."""
    w, v = _twist_log(T)
    out = np.eye(4)
    out[:3, :3] = cv2.Rodrigues(s * w)[0]
    out[:3, 3] = _V(s * w) @ (s * v)
    return out


def _translation(v: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = v
    return T
