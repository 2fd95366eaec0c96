"""The geofence: no setpoint ever leaves the area volume.

The area volume (area frame, metres) is ``x in [0, size_x_m]``, ``y in [0, size_y_m]``,
``z in [z_min_m, z_max_m]``, from :class:`sim.config.AreaConfig`. A target outside is clamped to
the nearest point inside; a target with NaN or infinite coordinates has no nearest point and is
refused with a ValueError.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from sim.config import AreaConfig


def clamp_to_area(
    target_m: Sequence[float], area: AreaConfig
) -> tuple[tuple[float, float, float], bool]:
    """Clamp an area-frame target ``(x_m, y_m, z_m)`` into the area volume.

    Returns ``(clamped, was_clamped)``. Raises ValueError for a target that is not three finite
    numbers.
    """
    if len(target_m) != 3:
        raise ValueError(f"target must be (x_m, y_m, z_m), got {target_m!r}")
    x_m, y_m, z_m = (float(v) for v in target_m)
    if not all(math.isfinite(v) for v in (x_m, y_m, z_m)):
        raise ValueError(f"target must be finite, got {(x_m, y_m, z_m)!r}")
    clamped = (
        min(max(x_m, 0.0), area.size_x_m),
        min(max(y_m, 0.0), area.size_y_m),
        min(max(z_m, area.z_min_m), area.z_max_m),
    )
    return clamped, clamped != (x_m, y_m, z_m)
