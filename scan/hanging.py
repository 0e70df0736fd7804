"""What hangs the phantom in the pictures (its tubes, up to a holder out of view) taken off the carved hull.

The rig hangs the phantom by its tubes (the paper's Fig. 4): in every picture they run from the gland's base up
and out of the picture's top edge. The silhouettes keep them (:mod:`phantom.scan.silhouette` makes whatever is
neither backdrop nor phantom opaque, since a tube in front of the gland hides the gland behind it), so the hull
is the gland with a column of tubes standing on its base, cut where the pictures end. The column is taken off
at the gland's base, a plane across the hanging axis (the orbit's axis, pointing up the pictures):

- the hull's cross-section area along the axis (its inside, a voxel's occupancy read from the field, binned by
  height) is small and steady along the column, and grows where the gland begins;
- the column's area is the median over a stretch of it (:data:`COLUMN_WINDOW_MM` below the top, less the
  ragged :data:`TOP_MARGIN_MM` where the pictures end at different heights), and it must be steady there
  (within :data:`STEADY_SPREAD` of it: a gland's own top is not);
- going down, the gland is reached where the area first exceeds :data:`JUNCTION_FACTOR` times the column's;
  the base is the highest of the steepest rises of the area within :data:`BASE_SEARCH_MM` below that (the hull
  fills in between the tubes just above a flat base, where the views from above see the gland behind them),
  placed within its bin by the bin's share of the rise; the hull above that plane is dropped (the field raised
  to the plane's).

It is done only where most silhouettes reach the picture's top edge (something hangs the phantom in view); a
phantom seen whole in every picture is left as carved. What it costs: the gland above the plane is lost, i.e.
nothing for a gland whose base is flat (as the model's, clamped at z = 20 mm) and, for a gland rounded where the
tubes enter, the cap whose section is below the threshold (about 0.1 % of 26 ml for tubes of 4.4 mm into a dome
of 20 mm); within a voxel of the base, half a voxel of the base's area (0.15 mm x 70-150 mm^2: 0.05 %). It
assumes the column is narrower than the gland's base: tubes spread wider than the base would be cut lower, with
the base's slab (documented in scan/README.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from phantom.model.arrays import FloatArray
from phantom.scan.camera import Rig
from phantom.scan.carve import Grid

#: The column's area is the median over this height (mm) of it ...
COLUMN_WINDOW_MM = 8.0
#: ... below this much of its top (mm), where the pictures end at different heights.
TOP_MARGIN_MM = 3.0
#: The column is steady: its section varies by less than this share of it along the window.
STEADY_SPREAD = 0.3
#: The gland begins where the section first exceeds this many times the column's.
JUNCTION_FACTOR = 1.5
#: The base is looked for this far (mm) below where the section crosses the threshold.
BASE_SEARCH_MM = 2.0
#: ... at the highest rise of the section at least this share of the steepest there (a rounded gland's section
#: grows about as fast at every height: its highest, not a lower one the noise makes steeper).
STEEP_SHARE = 0.6
#: Something hangs the phantom when at least this share of the silhouettes reach the picture's top edge.
HANGING_SHARE = 0.5


@dataclass(frozen=True)
class Hanging:
    """The column taken off: the hanging axis (unit, up, the rig's frame), the cut's height along it (mm, from the
    rig's origin), the column's cross-section (mm^2) and the volume taken off (ml)."""

    up: FloatArray
    cut_mm: float
    column_area_mm2: float
    removed_ml: float

    def to_json(self) -> dict[str, object]:
        return {"up": self.up.tolist(), "cut_mm": self.cut_mm, "column_area_mm2": self.column_area_mm2,
                "removed_ml": self.removed_ml}


def hanging_axis(rig: Rig) -> FloatArray:
    """The orbit's axis pointing up the pictures (against the image's y at orbit 0 of the first pass)."""
    down = rig.elevations[0].pose.rotation[1]  # the camera's y (down the picture) in the rig's frame
    axis = np.asarray(rig.axis_direction, float)
    up: FloatArray = axis if float(axis @ down) < 0 else -axis
    return up


def _heights_mm(grid: Grid, up: FloatArray) -> np.ndarray:
    """Each grid point's height along ``up`` (mm), float32, the grid's shape."""
    nx, ny, nz = grid.values.shape
    h = grid.spacing_mm
    heights: np.ndarray = (np.float32(grid.origin_mm @ up)
                           + np.float32(h * up[0]) * np.arange(nx, dtype=np.float32)[:, None, None]
                           + np.float32(h * up[1]) * np.arange(ny, dtype=np.float32)[None, :, None]
                           + np.float32(h * up[2]) * np.arange(nz, dtype=np.float32)[None, None, :])
    return heights


def section_areas(grid: Grid, up: FloatArray) -> tuple[np.ndarray, np.ndarray]:
    """The hull's cross-section area (mm^2) at heights along ``up`` (bins of a voxel): bin centres (mm), areas."""
    h = grid.spacing_mm
    occupancy = np.clip(0.5 - grid.values / h, 0.0, 1.0)
    inside = occupancy > 0
    heights = _heights_mm(grid, up)[inside]
    low, high = float(heights.min()), float(heights.max())
    edges = np.arange(low - h, high + 2 * h, h)
    volume, _ = np.histogram(heights, bins=edges, weights=occupancy[inside].astype(np.float64) * h ** 3)
    return 0.5 * (edges[:-1] + edges[1:]), volume / h


def find_base(heights_mm: np.ndarray, areas_mm2: np.ndarray) -> tuple[float, float] | None:
    """The gland's base under a hanging column: (its height, the column's area), or None where the section
    profile shows no column (too short, or no narrower than what is below it)."""
    filled = np.flatnonzero(areas_mm2 > 0)
    if len(filled) == 0:
        return None
    top = heights_mm[filled[-1]]
    window = (heights_mm <= top - TOP_MARGIN_MM) & (heights_mm >= top - TOP_MARGIN_MM - COLUMN_WINDOW_MM)
    if np.count_nonzero(window) < 3:
        return None
    column = float(np.median(areas_mm2[window]))
    if not column > 0 or np.ptp(areas_mm2[window]) > STEADY_SPREAD * column:
        return None  # not a column of tubes: the hull changes its section along it
    threshold = JUNCTION_FACTOR * column
    below = np.flatnonzero((heights_mm < top - TOP_MARGIN_MM) & (areas_mm2 > threshold))
    if len(below) == 0:
        return None
    crossing = below[-1]  # the highest bin over the threshold: the column ends just above it
    if crossing + 2 >= len(areas_mm2):
        return None
    # the hull fills in between the tubes just above the base (the views from above see the gland behind them):
    # the base is the steepest rise of the section within a little below the crossing (a flat base's step; the
    # crossing itself where the gland is rounded and its section grows less steeply downwards)
    h = float(heights_mm[1] - heights_mm[0])
    lowest = max(0, crossing - int(np.ceil(BASE_SEARCH_MM / h)))
    rises = areas_mm2[lowest:crossing + 1] - areas_mm2[lowest + 1:crossing + 2]
    steep = np.flatnonzero(rises >= STEEP_SHARE * rises.max())
    full = lowest + int(steep[-1])  # the highest bin the gland fills; the one above it holds its base
    above, over = areas_mm2[full + 1], areas_mm2[min(full + 2, len(areas_mm2) - 1)]
    share = (above - over) / (areas_mm2[full] - over) if areas_mm2[full] > over else 0.0
    base = float(heights_mm[full] + 0.5 * h + np.clip(share, 0.0, 1.0) * h)
    return base, column


def cut_column(grid: Grid, rig: Rig) -> tuple[Grid, Hanging | None]:
    """The grid with the hanging column taken off above the gland's base (see the module docstring), and what was
    taken; the grid as it was, and None, where the profile shows no column."""
    up = hanging_axis(rig)
    heights, areas = section_areas(grid, up)
    found = find_base(heights, areas)
    if found is None:
        return grid, None
    base_mm, column_mm2 = found
    values = np.maximum(grid.values, _heights_mm(grid, up) - np.float32(base_mm))
    h = grid.spacing_mm
    removed_mm3 = float(np.sum(np.clip(0.5 - grid.values / h, 0, 1)) - np.sum(np.clip(0.5 - values / h, 0, 1))) * h ** 3
    return Grid(grid.origin_mm, grid.spacing_mm, values), Hanging(up, base_mm, column_mm2, removed_mm3 / 1e3)
