"""Hand-built scenes whose specimens, containers and blobs follow from their construction (shared by the tests of
:func:`~napari_unwind.segmentation.specimens` and :func:`~napari_unwind.segmentation.candidates`)."""

from __future__ import annotations

import numpy as np


def rods_in_tube(*, ball_on_border: bool) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """A tube (axis 0, not touching the border) around two rods, a rod outside it, and a ball: inside the volume
    away from every face, or cut by the face k = 0 (``ball_on_border``). Returns the volume and each part's mask."""
    shape = (44, 44, 44)
    vol = np.zeros(shape, np.float32)
    i, j, k = np.indices(shape)
    rho = np.hypot(j - 21.5, k - 21.5)
    ball = (i - 22) ** 2 + (j - 22) ** 2 + k**2 <= 16 if ball_on_border else \
        (i - 22) ** 2 + (j - 36) ** 2 + (k - 36) ** 2 <= 9
    parts = {
        "tube": (rho >= 12) & (rho <= 14) & (i >= 4) & (i < 40),
        "rod_a": (i >= 8) & (i < 36) & (abs(j - 17) <= 1) & (abs(k - 21) <= 1),
        "rod_b": (i >= 8) & (i < 34) & (abs(j - 26) <= 1) & (abs(k - 22) <= 1),
        "rod_out": (i >= 10) & (i < 34) & (abs(j - 3) <= 1) & (abs(k - 3) <= 1),
        "ball": ball,
    }
    for m, v in zip(parts.values(), (5.0, 10.0, 9.0, 8.0, 7.0)):
        vol[m] = v
    return vol, parts
