"""A small CT for the CT cache's and the renderer's volume tests: soft tissue with a bone block."""

from __future__ import annotations

import numpy as np

from sim.ct.volume import CTVolume


def small_ct(seed: int, *, fractional: bool = False) -> CTVolume:
    """A 24 x 20 x 16 CT of soft tissue with a bone block whose place depends on the seed."""
    rng = np.random.default_rng(seed)
    hu = rng.integers(-100, 100, (24, 20, 16)).astype(np.float32)
    i = 4 + seed % 8
    hu[i:i + 8, 5:12, 4:10] = 1200.0
    if fractional:
        hu += 0.25
    affine = np.diag([1.5, 1.5, 2.0, 1.0])
    affine[:3, 3] = (-20.0, -15.0, 10.0)
    return CTVolume(hu=hu, affine=affine, source=f"test:{seed}")
