"""The shared number validator, and the two callers that used private twins of it."""

import math

import numpy as np
import pytest

from napari_unwind.datasets import fish_phantom
from napari_unwind.editing import EditModel
from napari_unwind.errors import InvalidInputError, finite_number


@pytest.mark.parametrize("value, expected", [(3, 3.0), (-2.5, -2.5), (np.float32(0.25), 0.25), ("1.5", 1.5),
                                             (np.int64(7), 7.0)])
def test_finite_number_accepts(value, expected):
    out = finite_number("x", value)
    assert type(out) is float and out == expected


@pytest.mark.parametrize("value, words", [
    (math.nan, "finite"), (math.inf, "finite"), (-math.inf, "finite"), ("abc", "number"), (None, "number"),
    (True, "number"), (np.bool_(False), "number"), ([3.0], "number"), (np.array([1.0, 2.0]), "number"),
])
def test_finite_number_refuses_naming_the_value(value, words):
    with pytest.raises(InvalidInputError) as info:
        finite_number("angle", value)
    text = str(info.value)
    assert text.startswith("angle must be") and words in text and repr(value) in text


@pytest.mark.parametrize("bad", [math.nan, True, [10.0]])
def test_fish_phantom_twist_is_a_finite_scalar(bad):
    with pytest.raises(InvalidInputError, match="twist must be"):
        fish_phantom(twist=bad)


def test_edit_model_refuses_a_nan_move_and_keeps_the_deformation():
    from napari_unwind.deformation import Deformation

    n = 5
    pos = np.stack([np.linspace(5, 45, n), np.full(n, 10.0), np.full(n, 10.0)], axis=1)
    frame = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])  # u, v, n (n along axis0)
    model = EditModel(Deformation.from_keyframes(pos, np.stack([frame] * n), (4.0, 4.0)))
    before = model.deformation
    with pytest.raises(InvalidInputError, match="dx must be a finite number"):
        model.move(math.nan, 0.0)
    assert model.deformation is before
