"""The simulated room: walls, the furniture band along them, and the floor surfaces.

Shared by the wheelchair simulator (the driver keeps the chair out of the furniture band,
the chair looks up the floor under it) and the RGB-D renderer (walls, furniture placed in
the band, floor texture per surface). Pure Python, no ROS.

Frame: the room's ``odom``-like world frame, x forward from the chair's start pose, y to
the left, z up (REP-103). The chair starts at the origin facing +x.

Default geometry: a 12 m x 9 m rectangle, x in [-6, 6] m, y in [-4.5, 4.5] m. Furniture
(tables, shelves, plants) stands in a band of ``furniture_band`` = 0.6 m along every wall;
the chair's footprint (``FOOTPRINT_LENGTH`` x ``FOOTPRINT_WIDTH``, centred on the drive
axle of a mid-wheel-drive chair) must stay out of it.

Floor: ``base_surface`` everywhere except inside ``patches`` (axis-aligned rectangles,
each with its own surface). ``room_for_surface("hybrid")`` lays carpet patches on a tiled
atrium floor so that a drive crosses both, like the paper's hybrid recordings.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

SURFACES = ("tile", "carpet")
"""Floor materials the chair model has parameters for."""

RECORDING_SURFACES = ("tile", "carpet", "hybrid")
"""Recording conditions of the paper: one floor, or an atrium with patches of both."""

FOOTPRINT_LENGTH = 1.2
"""Chair + user footprint length along the chair's x axis (m), centred on the axle."""

FOOTPRINT_WIDTH = 0.7
"""Chair footprint width (m)."""

FOOTPRINT_RADIUS = math.hypot(FOOTPRINT_LENGTH / 2.0, FOOTPRINT_WIDTH / 2.0)
"""Distance from the chair's reference point to a footprint corner (m), about 0.69."""


@dataclass(frozen=True)
class Patch:
    """An axis-aligned rectangle of floor material ``surface`` (metres, world frame)."""

    x_min: float
    y_min: float
    x_max: float
    y_max: float
    surface: str

    def __post_init__(self) -> None:
        if not (self.x_max > self.x_min and self.y_max > self.y_min):
            raise ValueError(f"patch has no area: {self}")
        if self.surface not in SURFACES:
            raise ValueError(f"unknown surface {self.surface!r}; expected one of {SURFACES}")

    def contains(self, x: float, y: float) -> bool:
        return self.x_min <= x <= self.x_max and self.y_min <= y <= self.y_max


@dataclass(frozen=True)
class Room:
    """A rectangular room with a furniture band along the walls and a floor map.

    Attributes:
        x_min, x_max, y_min, y_max: wall positions (m).
        furniture_band: depth of the band along each wall where furniture may stand (m).
        base_surface: floor material outside the patches ("tile" or "carpet").
        patches: rectangles of another floor material (the first match wins).
        wall_height: for the renderer (m).
    """

    x_min: float = -6.0
    x_max: float = 6.0
    y_min: float = -4.5
    y_max: float = 4.5
    furniture_band: float = 0.6
    base_surface: str = "tile"
    patches: tuple[Patch, ...] = ()
    wall_height: float = 2.6

    def __post_init__(self) -> None:
        if self.base_surface not in SURFACES:
            raise ValueError(
                f"unknown surface {self.base_surface!r}; expected one of {SURFACES}"
            )
        if self.furniture_band < 0.0:
            raise ValueError("furniture_band must be >= 0")
        free = 2.0 * (self.furniture_band + FOOTPRINT_RADIUS) + 1.0
        if self.x_max - self.x_min < free or self.y_max - self.y_min < free:
            raise ValueError(
                f"room {self.x_max - self.x_min:.2f} m x {self.y_max - self.y_min:.2f} m is "
                f"too small for a chair with a {self.furniture_band} m furniture band"
            )
        if not (self.x_min < 0.0 < self.x_max and self.y_min < 0.0 < self.y_max):
            raise ValueError("the room must contain the start pose (the origin)")

    @property
    def centre(self) -> tuple[float, float]:
        return (0.5 * (self.x_min + self.x_max), 0.5 * (self.y_min + self.y_max))

    def surface_at(self, x: float, y: float) -> str:
        """Floor material under the point (x, y)."""
        for patch in self.patches:
            if patch.contains(x, y):
                return patch.surface
        return self.base_surface

    def wall_distance(self, x: float, y: float) -> float:
        """Distance (m) from (x, y) to the nearest wall (negative outside the room)."""
        return min(x - self.x_min, self.x_max - x, y - self.y_min, self.y_max - y)

    @property
    def free_box(self) -> tuple[float, float, float, float]:
        """(x_lo, x_hi, y_lo, y_hi) of the free floor: the walls less the furniture band.
        Its edges are the fronts of the furniture, the obstacles a scanner sees."""
        b = self.furniture_band
        return (self.x_min + b, self.x_max - b, self.y_min + b, self.y_max - b)

    def contact(self, x: float, y: float, theta: float) -> bool:
        """The footprint at (x, y, theta) overlaps the furniture (or a wall)."""
        return self.footprint_clearance(x, y, theta) < self.furniture_band

    def overlap(self, x: float, y: float, theta: float) -> float:
        """How far (m) the footprint at (x, y, theta) reaches into the furniture; 0 if free."""
        return max(0.0, self.furniture_band - self.footprint_clearance(x, y, theta))

    def footprint_clearance(self, x: float, y: float, theta: float) -> float:
        """Distance (m) from the chair footprint at pose (x, y, theta) to the nearest wall.

        The footprint is the ``FOOTPRINT_LENGTH`` x ``FOOTPRINT_WIDTH`` rectangle centred
        on (x, y). It is clear of the furniture when the result is >= ``furniture_band``.
        """
        c, s = abs(math.cos(theta)), abs(math.sin(theta))
        half_x = 0.5 * (FOOTPRINT_LENGTH * c + FOOTPRINT_WIDTH * s)  # axis-aligned extent
        half_y = 0.5 * (FOOTPRINT_LENGTH * s + FOOTPRINT_WIDTH * c)
        return min(
            x - half_x - self.x_min,
            self.x_max - x - half_x,
            y - half_y - self.y_min,
            self.y_max - y - half_y,
        )


def room_for_surface(surface: str) -> Room:
    """The default room laid with the floor of a recording condition.

    ``"tile"`` and ``"carpet"``: one material wall to wall. ``"hybrid"``: a tiled atrium
    with carpet rugs covering about 40 % of the drivable area, so that any drive of a
    minute or more crosses both materials.
    """
    if surface in SURFACES:
        return Room(base_surface=surface)
    if surface != "hybrid":
        raise ValueError(
            f"unknown surface {surface!r}; expected one of {RECORDING_SURFACES}"
        )
    rugs = (
        Patch(-4.8, 0.4, -1.2, 3.9, "carpet"),
        Patch(1.0, -3.9, 4.8, -0.6, "carpet"),
        Patch(-1.0, -1.5, 0.8, 1.2, "carpet"),
        Patch(2.2, 1.2, 5.4, 3.9, "carpet"),
    )
    return Room(base_surface="tile", patches=rugs)
