"""Small NumPy helpers shared by the pattern builders."""
from __future__ import annotations

import numpy as np

__all__ = ["sorted_unique"]


def sorted_unique(a: np.ndarray) -> np.ndarray:
    """The sorted distinct values of the 1-D array ``a``, as ``np.unique(a)``.

    A stable sort (which merges the already sorted runs that concatenated CSR keys consist of) and a mask:
    NumPy >= 2.3 answers a plain ``np.unique`` of integers by hashing, 10-20x slower than this on the millions
    of keys of a large cloth's sparse pattern (3.8 s against 0.2 s for 3e6 keys)."""
    s = np.sort(np.asarray(a).reshape(-1), kind="stable")
    if s.shape[0] < 2:
        return s
    keep = np.empty(s.shape[0], dtype=bool)
    keep[0] = True
    np.not_equal(s[1:], s[:-1], out=keep[1:])
    return s[keep]
