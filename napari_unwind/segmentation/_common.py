"""What the join tree and its simplification share (below both, so neither imports the other's users)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..errors import InvalidInputError

__all__ = ["MAX_FEATURES", "check_features_count"]

#: Largest number of features a simplification may keep (the original's slider ran 1-100).
MAX_FEATURES = 100


def check_features_count(k: Any) -> int:
    """Validate a number of features: an integer in 1..100."""
    if isinstance(k, (bool, np.bool_)) or not isinstance(k, (int, np.integer)):
        raise InvalidInputError(f"the number of features must be an integer between 1 and {MAX_FEATURES}, got {k!r}")
    if not 1 <= int(k) <= MAX_FEATURES:
        raise InvalidInputError(f"the number of features must be between 1 and {MAX_FEATURES}, got {int(k)}")
    return int(k)
