"""napari sample-data contributions: the phantoms, each with its ground-truth mask or labels."""

from __future__ import annotations

import numpy as np

from ..io import Volume
from ._layers import image_layer, labels_layer

__all__ = ["sample_fish", "sample_tank", "sample_cylinder"]


def _layers(volume: np.ndarray, labels: np.ndarray, spacing, unit, name: str, truth: str) -> list:
    return [
        image_layer(Volume(volume, spacing=spacing, unit=unit), name=name),
        labels_layer(labels, spacing=spacing, unit=unit, name=f"{name} {truth}", visible=False),
    ]


def sample_fish() -> list:
    """A bent and twisted fish in a tube, with its true mask."""
    from ..datasets import fish_phantom

    p = fish_phantom()
    return _layers(p.volume, p.mask.astype(np.uint8), p.spacing, p.unit, "fish phantom", "true mask")


def sample_cylinder() -> list:
    """The paper's synthetic experiment: a cylinder bent along a sine wave."""
    from ..datasets import cylinder_phantom

    p = cylinder_phantom()
    return _layers(p.volume, p.mask.astype(np.uint8), p.spacing, p.unit, "sine cylinder", "true mask")


def sample_tank() -> list:
    """A tube holding several fish that touch nothing, with one label per fish."""
    from ..datasets import tank_phantom

    t = tank_phantom()
    return _layers(t.volume, t.labels, t.spacing, t.unit, "tank", "true fish")
