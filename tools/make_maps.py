"""Remake the shipped map scenes (map_server YAML + PGM beside a scene file) in gpmppi/data/:

* `map_rooms` / `scene_rooms.yaml`: a 10 x 8 m floor at 5 cm: two rooms joined by a doorway, a corridor beyond with
  its own opening, boxes and pillars about;
* `map_paper` / `scene_paper_grid.yaml`: the paper's obstacle scene (gpmppi/data/scene_paper.yaml) rasterised to
  5 cm, for comparing the costmap critic with the circles.

`python -m tools.make_maps` (writes the files; the same bytes every time).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gpmppi.costmap import Costmap, rasterise_circles, write_map
from gpmppi.scenarios import PAPER_OBSTACLES

DATA = Path(__file__).resolve().parents[1] / "gpmppi" / "data"
RES = 0.05


def _box(values: np.ndarray, x0: float, y0: float, x1: float, y1: float) -> None:
    """Mark the cells whose centre lies in [x0, x1] x [y0, y1] [m] (grid origin at 0, 0) lethal."""
    h, w = values.shape
    cx = (np.arange(w) + 0.5) * RES
    cy = (np.arange(h) + 0.5) * RES
    values[np.ix_((cy >= y0) & (cy <= y1), (cx >= x0) & (cx <= x1))] = 100


def _disc(values: np.ndarray, x: float, y: float, r: float) -> None:
    h, w = values.shape
    gx, gy = np.meshgrid((np.arange(w) + 0.5) * RES, (np.arange(h) + 0.5) * RES)
    values[(gx - x) ** 2 + (gy - y) ** 2 < r * r] = 100


def rooms() -> Costmap:
    """Outer walls; a wall at x = 4 m with a 1.2 m doorway at y 5.2-6.4; a wall at x = 6.5 m with a 1.2 m opening at
    y 1.2-2.4 (the way to the goal zig-zags); boxes and pillars in the rooms."""
    values = np.zeros((160, 200), dtype=np.int16)
    t = 0.1  # wall thickness [m]
    _box(values, 0.0, 0.0, 10.0, t)
    _box(values, 0.0, 8.0 - t, 10.0, 8.0)
    _box(values, 0.0, 0.0, t, 8.0)
    _box(values, 10.0 - t, 0.0, 10.0, 8.0)
    _box(values, 4.0, 0.0, 4.0 + t, 5.2)
    _box(values, 4.0, 6.4, 4.0 + t, 8.0)
    _box(values, 6.5, 0.0, 6.5 + t, 1.2)
    _box(values, 6.5, 2.4, 6.5 + t, 8.0)
    _box(values, 1.6, 2.6, 2.4, 3.2)  # boxes in the first room
    _box(values, 2.8, 4.4, 3.3, 6.0)
    _disc(values, 1.2, 5.5, 0.35)  # pillars
    _disc(values, 5.3, 3.2, 0.3)
    _disc(values, 5.0, 1.6, 0.25)
    _box(values, 7.6, 4.0, 8.6, 4.6)  # a box in the last room
    _disc(values, 8.4, 2.2, 0.3)
    return Costmap(values, RES, (-0.5, -0.5, 0.0))


def paper() -> Costmap:
    return rasterise_circles(PAPER_OBSTACLES, RES, np.array([-1.5, -1.5]), np.array([9.0, 7.5]))


SCENE_ROOMS = """# A floor plan as a map_server map (map_rooms.yaml + .pgm; remade by `python -m tools.make_maps`): two
# rooms joined by a doorway, a corridor beyond with its own opening, boxes and pillars.
name: rooms
start: {x: 0.5, y: 1.0, yaw: 0.0}   # [m, m, rad]; the robot starts at rest
goal: [8.5, 6.5]                     # [m]
tolerance: 0.5                       # goal radius [m]
map: map_rooms.yaml                  # obstacles: the map's occupied cells
"""

SCENE_PAPER_GRID = """# The paper's obstacle scene (scene_paper.yaml) with its circles rasterised to a 5 cm map_server
# map (map_paper.yaml + .pgm; remade by `python -m tools.make_maps`): the costmap critic against the circles.
name: paper_grid
start: {x: 0.0, y: 0.0, yaw: 0.7853981634}
goal: [7.0, 5.0]
tolerance: 0.5
map: map_paper.yaml
"""


def main() -> None:
    write_map(rooms(), DATA / "map_rooms.yaml", "map_rooms.pgm")
    write_map(paper(), DATA / "map_paper.yaml", "map_paper.pgm")
    (DATA / "scene_rooms.yaml").write_text(SCENE_ROOMS)
    (DATA / "scene_paper_grid.yaml").write_text(SCENE_PAPER_GRID)


if __name__ == "__main__":
    main()
