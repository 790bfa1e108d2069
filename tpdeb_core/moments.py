"""Running moments (count, mean, M2) and Chan et al.'s parallel merge, in numpy.

Actors and the replay server compute the moments of what they collect and ingest; the learner's
normalisers (`tpdeb_core.model.RunningMeanStd`) fold them in. Kept apart from the networks so
that processes without torch use the same arithmetic.
"""

from __future__ import annotations

import numpy as np

NORM_EPSILON = 1e-8  # added to the variance before the square root, everywhere


def batch_moments(x: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(count, mean, M2) of a batch along axis 0, the unit that normalisers merge."""
    x = np.asarray(x, dtype=np.float64)
    x = x.reshape(x.shape[0], -1) if x.ndim > 1 else x.reshape(-1, 1)
    mean = x.mean(axis=0)
    m2 = ((x - mean) ** 2).sum(axis=0)
    return float(x.shape[0]), mean, m2


def merge_moments(a: tuple, b: tuple) -> tuple[float, np.ndarray, np.ndarray]:
    """Chan et al.'s parallel combination of two (count, mean, M2) triples."""
    n_a, mean_a, m2_a = a
    n_b, mean_b, m2_b = b
    if n_b <= 0:
        return float(n_a), np.asarray(mean_a, np.float64), np.asarray(m2_a, np.float64)
    n = n_a + n_b
    delta = np.asarray(mean_b, np.float64) - mean_a
    mean = mean_a + delta * (n_b / n)
    m2 = m2_a + np.asarray(m2_b, np.float64) + delta**2 * (n_a * n_b / n)
    return float(n), mean, m2


def variance(count: float, m2: np.ndarray) -> np.ndarray:
    """M2 / count, or ones until two samples exist (a normaliser that does nothing yet)."""
    m2 = np.asarray(m2, np.float64)
    return m2 / count if count >= 2 else np.ones_like(m2)


def inverse_std(count: float, m2: np.ndarray, epsilon: float = NORM_EPSILON) -> np.ndarray:
    """1 / √(variance + ε): what a normaliser divides by (and the reward scale is)."""
    return 1.0 / np.sqrt(variance(count, m2) + epsilon)
