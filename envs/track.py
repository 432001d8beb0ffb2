"""Geometry of a stadium-shaped lane (two straights joined by two half circles) and its ground texture.

Coordinates in metres, the loop centred on the origin, straights parallel to x. Arc length s runs
along the centre line in the direction of travel from the start line at the middle of the lower
straight (counter-clockwise, or clockwise with ``clockwise=True``). Cross-track error is positive to
the left of the direction of travel; headings are radians from +x.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def wrap_angle(angle: float) -> float:
    """Angle in [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


@dataclass(frozen=True)
class TrackSpec:
    """The stadium lane's geometry, in metres; ValueError for one that cannot be drawn."""

    straight_length: float = 2.0  # m, each straight
    radius: float = 1.0  # m, of the centre line on the bends
    lane_width: float = 0.5  # m, between the outer edges of the two edge tapes
    tape_width: float = 0.03  # m, edge markings, inside the lane width
    clockwise: bool = False
    margin: float = 1.0  # m of floor drawn around the lane

    def __post_init__(self) -> None:
        sizes = (self.straight_length, self.tape_width, self.margin)
        if not (all(v >= 0 for v in sizes) and self.radius > self.lane_width / 2 and self.lane_width > 2 * self.tape_width):  # NaN fails too
            raise ValueError(f"impossible track: {self}")

    @property
    def length(self) -> float:
        """Length of the centre line, m."""
        return 2.0 * self.straight_length + 2.0 * math.pi * self.radius

    def _project_ccw(self, x: float, y: float) -> tuple[float, float, float]:
        half, r = self.straight_length / 2.0, self.radius
        if -half <= x <= half:
            if y <= 0.0:  # lower straight, travelling +x from the start line at x = 0
                s = x if x >= 0.0 else self.length + x
                return s, y + r, 0.0
            return half + math.pi * r + (half - x), r - y, math.pi  # upper straight, travelling -x
        if x > half:  # right bend, centre (half, 0)
            phi = math.atan2(y, x - half)  # in (-pi/2, pi/2)
            return half + r * (phi + math.pi / 2.0), r - math.hypot(x - half, y), phi + math.pi / 2.0
        phi = math.atan2(y, x + half) % (2.0 * math.pi)  # left bend, centre (-half, 0); phi in (pi/2, 3pi/2)
        return 3.0 * half + math.pi * r + r * (phi - math.pi / 2.0), r - math.hypot(x + half, y), phi + math.pi / 2.0

    def project(self, x: float, y: float) -> tuple[float, float, float]:
        """(arc length s in [0, length), cross-track error, centre-line heading) of the nearest centre-line point."""
        if not self.clockwise:
            s, cte, heading = self._project_ccw(x, y)
            return s % self.length, cte, wrap_angle(heading)
        s, cte, heading = self._project_ccw(x, -y)  # clockwise = the mirror image in y, left and right swapped
        return s % self.length, -cte, wrap_angle(-heading)

    def pose_at(self, s: float) -> tuple[float, float, float]:
        """(x, y, heading) of the centre line at arc length s."""
        half, r = self.straight_length / 2.0, self.radius
        s = s % self.length
        if s < half:
            x, y, heading = s, -r, 0.0
        elif s < half + math.pi * r:
            phi = (s - half) / r - math.pi / 2.0
            x, y, heading = half + r * math.cos(phi), r * math.sin(phi), phi + math.pi / 2.0
        elif s < 3.0 * half + math.pi * r:
            x, y, heading = half - (s - half - math.pi * r), r, math.pi
        elif s < 3.0 * half + 2.0 * math.pi * r:
            phi = (s - 3.0 * half - math.pi * r) / r + math.pi / 2.0
            x, y, heading = -half + r * math.cos(phi), r * math.sin(phi), phi + math.pi / 2.0
        else:
            x, y, heading = s - self.length, -r, 0.0
        if self.clockwise:
            y, heading = -y, -heading
        return x, y, wrap_angle(heading)

    def progress(self, s_from: float, s_to: float) -> float:
        """Signed distance travelled along the centre line, assuming less than half a lap per step."""
        return (s_to - s_from + self.length / 2.0) % self.length - self.length / 2.0

    @property
    def extent(self) -> tuple[float, float]:
        """Half sizes (x, y) of the drawn ground, m."""
        outer = self.radius + self.lane_width / 2.0 + self.margin
        return self.straight_length / 2.0 + outer, outer

    def texture(self, metres_per_pixel: float = 0.004) -> np.ndarray:
        """RGB uint8 image of the ground, row 0 at +y: light floor tiles, dark lane, white edge tape."""
        half_x, half_y = self.extent
        width, height = int(round(2 * half_x / metres_per_pixel)), int(round(2 * half_y / metres_per_pixel))
        xs = (np.arange(width) + 0.5) * metres_per_pixel - half_x
        ys = half_y - (np.arange(height) + 0.5) * metres_per_pixel
        x, y = np.meshgrid(xs, ys)
        half = self.straight_length / 2.0
        # distance from the centre line, for every pixel at once (the projection's cte, unsigned)
        radial = np.hypot(x - np.where(x > 0, half, -half), y)  # from the nearer bend's centre
        offset = np.where(np.abs(x) <= half, np.abs(np.abs(y) - self.radius), np.abs(radial - self.radius))
        tiles = ((np.floor(x / 0.3) + np.floor(y / 0.3)) % 2).astype(np.uint8)
        image = np.where(tiles[..., None] == 1, np.uint8(196), np.uint8(178)) * np.ones(3, dtype=np.uint8)
        lane = offset <= self.lane_width / 2.0
        tape = lane & (offset >= self.lane_width / 2.0 - self.tape_width)
        image[lane] = (38, 38, 42)
        image[tape] = (235, 235, 235)
        return np.ascontiguousarray(image)
