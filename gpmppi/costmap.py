"""Obstacles as an occupancy grid (a costmap): the grid, what the kernels read of it, and map_server map files.

A `Costmap` is a grid of values row-major from its origin cell, as nav_msgs/OccupancyGrid holds them: row r,
column c is the cell whose corner nearest the origin lies at (c, r) * resolution in the grid's frame, the grid's
frame placed at `origin` (x, y, yaw) in the world. Values are 0 (free) .. `lethal` and above (an obstacle); a negative
value is unknown (counted as free: the critic prices known cost only).

What the kernels read (`kernel_arrays`, computed once per grid): per cell its value as a fraction of `lethal`
(0..1, unknown 0) and the distance [m] from its centre to the nearest lethal cell's centre (a distance transform,
scipy.ndimage.distance_transform_edt), float32; and the grid's frame. The critic compares the distance at a rollout
point (bilinear between cell centres) with the robot radius plus the chance constraint's quantile radius of that
step (`lethal_radius`).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["Costmap", "CostmapError", "NO_GRID", "lethal_radius", "load_map_yaml", "rasterise_circles", "read_pgm"]

# what the kernels read where there is no grid: one free cell, and a frame whose first number (0) says "no grid"
NO_GRID = (np.zeros((1, 1, 2), dtype=np.float32), np.zeros(6))


class CostmapError(ValueError):
    """A grid that cannot be used: the message names what is wrong and what to do."""


@dataclass(frozen=True, eq=False)
class Costmap:
    """An occupancy grid: `values` (height, width) row-major from the origin cell; `resolution` [m/cell]; `origin`
    (x [m], y [m], yaw [rad]) of the grid's corner cell (0, 0) in the world; values >= `lethal` are obstacles."""

    values: np.ndarray
    resolution: float
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    lethal: float = 100.0
    _arrays: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        v = np.asarray(self.values)
        if v.ndim != 2 or v.shape[0] < 1 or v.shape[1] < 1:
            raise CostmapError(f"costmap values must be a (height, width) grid, got shape {v.shape}")
        if not np.issubdtype(v.dtype, np.integer) and not np.all(np.isfinite(v)):
            raise CostmapError("costmap values must be finite numbers")
        if not (np.isfinite(self.resolution) and self.resolution > 0):
            raise CostmapError(f"costmap resolution must be a positive number of metres per cell, got "
                               f"{self.resolution}")
        o = tuple(float(a) for a in self.origin)
        if len(o) != 3 or not all(np.isfinite(o)):
            raise CostmapError(f"costmap origin must be 3 finite numbers (x, y, yaw), got {self.origin!r}")
        if not (np.isfinite(self.lethal) and self.lethal > 0):
            raise CostmapError(f"costmap lethal threshold must be > 0, got {self.lethal}")
        object.__setattr__(self, "values", np.ascontiguousarray(v, dtype=np.int16 if np.issubdtype(
            v.dtype, np.integer) else np.float32))
        object.__setattr__(self, "origin", o)

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.values.shape[0]), int(self.values.shape[1]))

    @property
    def lethal_cells(self) -> np.ndarray:
        """(height, width) bool: the obstacle cells."""
        return self.values >= self.lethal

    def digest(self) -> bytes:
        """What identifies the grid (its values, resolution, origin, threshold), for caches (computed once)."""
        if "digest" not in self._arrays:
            head = np.array([self.resolution, *self.origin, self.lethal, *self.shape], dtype=np.float64).tobytes()
            self._arrays["digest"] = hashlib.sha256(head + self.values.tobytes()).digest()
        return self._arrays["digest"]

    def cell_centres(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """World positions (n, 2) [m] of the centres of cells (rows, cols)."""
        gx = (np.asarray(cols, dtype=np.float64) + 0.5) * self.resolution
        gy = (np.asarray(rows, dtype=np.float64) + 0.5) * self.resolution
        ox, oy, yaw = self.origin
        c, s = np.cos(yaw), np.sin(yaw)
        return np.stack([ox + c * gx - s * gy, oy + s * gx + c * gy], axis=-1)

    def to_grid(self, points: np.ndarray) -> np.ndarray:
        """Positions (n, 2) in the grid's frame, in cells (cell (r, c) spans [c, c+1) x [r, r+1))."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        ox, oy, yaw = self.origin
        c, s = np.cos(yaw), np.sin(yaw)
        dx, dy = p[:, 0] - ox, p[:, 1] - oy
        return np.stack([c * dx + s * dy, -s * dx + c * dy], axis=1) / self.resolution

    def corners(self) -> np.ndarray:
        """The grid's four corners in the world (4, 2) [m]."""
        h, w = self.shape
        ox, oy, yaw = self.origin
        c, s = np.cos(yaw), np.sin(yaw)
        g = np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]]) * self.resolution
        return np.stack([ox + c * g[:, 0] - s * g[:, 1], oy + s * g[:, 0] + c * g[:, 1]], axis=1)

    def kernel_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(grid (height, width, 2) float32: value fraction, distance to the nearest lethal cell centre [m]; frame (6,)
        float64: 1 (a grid), origin x, y, cos yaw, sin yaw, 1 / resolution). Computed once per grid and kept, so that
        a plan hands the kernels the same arrays (the CUDA backend uploads an array only when it is a new one)."""
        if "kernel" not in self._arrays:
            lethal = self.lethal_cells
            grid = np.empty((*self.shape, 2), dtype=np.float32)
            grid[:, :, 0] = np.clip(self.values / self.lethal, 0.0, 1.0)
            if lethal.any():
                # here, not at the top: scipy.ndimage costs every service ~0.2 s to import, and few ever use a grid
                from scipy.ndimage import distance_transform_edt

                grid[:, :, 1] = distance_transform_edt(~lethal) * self.resolution
            else:
                grid[:, :, 1] = np.float32(1e9)  # no obstacle anywhere: far from everything
            ox, oy, yaw = self.origin
            frame = np.array([1.0, ox, oy, np.cos(yaw), np.sin(yaw), 1.0 / self.resolution])
            self._arrays["kernel"] = (grid, frame)
        return self._arrays["kernel"]

    def nearest_lethal(self, points: np.ndarray) -> np.ndarray:
        """The distance (n,) [m] from each point to the nearest lethal cell's centre, by brute force over every lethal
        cell (inf when there is none): the reference the kernels' interpolated distance is checked against."""
        rows, cols = np.nonzero(self.lethal_cells)
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        if rows.size == 0:
            return np.full(p.shape[0], np.inf)
        centres = self.cell_centres(rows, cols)
        out = np.empty(p.shape[0])
        for i in range(0, p.shape[0], 256):
            d = p[i:i + 256, None, :] - centres[None, :, :]
            out[i:i + 256] = np.sqrt(np.min(np.einsum("ncd,ncd->nc", d, d), axis=1))
        return out

    def clearance(self, points: np.ndarray, robot_radius: float = 0.0) -> np.ndarray:
        """Clearance (n,) [m] of the robot's disc at each point from the lethal cells (negative = overlap): a point in a
        lethal cell overlaps; elsewhere the distance to the nearest lethal cell's centre less half a cell's diagonal
        and the robot radius. Outside the grid: the distance as if the grid went on free."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        g = np.floor(self.to_grid(p)).astype(np.int64)
        h, w = self.shape
        inside = (g[:, 0] >= 0) & (g[:, 0] < w) & (g[:, 1] >= 0) & (g[:, 1] < h)
        in_lethal = np.zeros(p.shape[0], dtype=bool)
        in_lethal[inside] = self.lethal_cells[g[inside, 1], g[inside, 0]]
        d = self.nearest_lethal(p) - 0.5 * np.sqrt(2.0) * self.resolution - robot_radius
        return np.where(in_lethal, np.minimum(d, -1e-9), d)


def lethal_radius(robot_radius: float, resolution: float) -> float:
    """The distance from a lethal cell's centre within which the robot's disc may touch the cell: the robot radius
    plus half the cell's diagonal (the disc of that radius covers the square)."""
    return float(robot_radius + 0.5 * np.sqrt(2.0) * resolution)


def rasterise_circles(circles: np.ndarray, resolution: float, lo: np.ndarray, hi: np.ndarray) -> Costmap:
    """A grid over the box [lo, hi] [m] whose cells with their centre inside a circle (x, y, r) are lethal (100)."""
    lo = np.asarray(lo, dtype=np.float64)
    size = np.asarray(hi, dtype=np.float64) - lo
    w, h = (int(np.ceil(s / resolution)) for s in size)
    cx = lo[0] + (np.arange(w) + 0.5) * resolution
    cy = lo[1] + (np.arange(h) + 0.5) * resolution
    gx, gy = np.meshgrid(cx, cy)
    values = np.zeros((h, w), dtype=np.int16)
    for x, y, r in np.asarray(circles, dtype=np.float64).reshape(-1, 3):
        values[(gx - x) ** 2 + (gy - y) ** 2 < r * r] = 100
    return Costmap(values, resolution, (float(lo[0]), float(lo[1]), 0.0))


# ------------------------------------------------------------------------------------------- map_server files
def read_pgm(path: Path) -> np.ndarray:
    """A PGM image (P5 binary or P2 text, 8 or 16 bit) as (rows, cols) integers, top row first."""
    data = path.read_bytes()
    magic = data[:2]
    if magic not in (b"P5", b"P2"):
        raise CostmapError(f"map image {path}: not a PGM file (starts {magic!r}, expected P5 or P2)")
    fields: list[bytes] = []
    pos = 2
    while len(fields) < 3:  # width, height, maxval, between whitespace and # comments
        while pos < len(data) and data[pos:pos + 1].isspace():
            pos += 1
        if data[pos:pos + 1] == b"#":
            pos = data.find(b"\n", pos) + 1 if data.find(b"\n", pos) >= 0 else len(data)
            continue
        end = pos
        while end < len(data) and not data[end:end + 1].isspace():
            end += 1
        if end == pos:
            raise CostmapError(f"map image {path}: its header ends before width, height and maxval")
        fields.append(data[pos:end])
        pos = end
    try:
        w, h, maxval = (int(f) for f in fields)
    except ValueError as e:
        raise CostmapError(f"map image {path}: header {fields} is not width, height, maxval") from e
    if w <= 0 or h <= 0 or not 0 < maxval < 65536:
        raise CostmapError(f"map image {path}: width {w}, height {h}, maxval {maxval} out of range")
    if magic == b"P2":
        pixels = np.array(data[pos:].split(), dtype=np.int64)
    else:
        pos += 1  # the one whitespace byte after maxval
        dtype = np.dtype(">u2") if maxval > 255 else np.dtype(np.uint8)
        pixels = np.frombuffer(data, dtype=dtype, count=min(w * h, (len(data) - pos) // dtype.itemsize), offset=pos)
    if pixels.size != w * h:
        raise CostmapError(f"map image {path}: {pixels.size} pixels for {w} x {h}; the file is cut short")
    return pixels.reshape(h, w).astype(np.float64) / maxval * 255.0


def load_map_yaml(path: str | Path) -> Costmap:
    """A map_server map: its YAML (`image`, `resolution`, `origin` [x, y, yaw], `occupied_thresh`, `free_thresh`,
    `negate`) beside a PGM image, as map_server's trinary mode reads it: occupancy p = (255 - pixel) / 255
    (pixel / 255 with `negate`), > occupied_thresh: 100, < free_thresh: 0, else unknown (-1); the image's bottom row is
    the grid's row 0."""
    import yaml

    p = Path(path)
    if not p.is_file():
        raise CostmapError(f"map file {p}: not found")
    try:
        meta = yaml.safe_load(p.read_text())
    except yaml.YAMLError as e:
        raise CostmapError(f"map file {p}: not YAML ({e})") from e
    if not isinstance(meta, dict):
        raise CostmapError(f"map file {p}: expected a mapping with image, resolution, origin")
    missing = [k for k in ("image", "resolution", "origin") if k not in meta]
    if missing:
        raise CostmapError(f"map file {p}: missing {', '.join(missing)} (a map_server map YAML)")
    mode = meta.get("mode", "trinary")
    if mode != "trinary":
        raise CostmapError(f"map file {p}: mode {mode!r}; only map_server's trinary mode is read")
    image = p.parent / str(meta["image"])
    if image.suffix.lower() != ".pgm":
        raise CostmapError(f"map file {p}: image {image.name}: only PGM images are read; convert it to PGM")
    if not image.is_file():
        raise CostmapError(f"map file {p}: image {image} not found")
    try:
        origin = [float(v) for v in meta["origin"]]
        resolution = float(meta["resolution"])
        occ, free = float(meta.get("occupied_thresh", 0.65)), float(meta.get("free_thresh", 0.196))
        negate = bool(int(meta.get("negate", 0)))
    except (TypeError, ValueError) as e:
        raise CostmapError(f"map file {p}: resolution, origin, thresholds must be numbers ({e})") from e
    if len(origin) != 3:
        raise CostmapError(f"map file {p}: origin must be [x, y, yaw], got {meta['origin']!r}")
    if not 0.0 <= free < occ <= 1.0:
        raise CostmapError(f"map file {p}: need 0 <= free_thresh < occupied_thresh <= 1, got {free}, {occ}")
    pixels = read_pgm(image)[::-1]  # the image's top row is the map's last
    occupancy = pixels / 255.0 if negate else (255.0 - pixels) / 255.0
    values = np.full(pixels.shape, -1, dtype=np.int16)
    values[occupancy > occ] = 100
    values[occupancy < free] = 0
    return Costmap(values, resolution, (origin[0], origin[1], origin[2]))


def write_map(costmap: Costmap, yaml_path: Path, image_name: str) -> None:
    """Write a map_server map (YAML and PGM beside it) of a grid of 0 / 100 / -1 cells."""
    v = costmap.values[::-1]
    pixels = np.full(v.shape, 205, dtype=np.uint8)  # unknown: map_server's grey
    pixels[v >= costmap.lethal] = 0
    pixels[(v >= 0) & (v < costmap.lethal)] = 254
    h, w = pixels.shape
    (yaml_path.parent / image_name).write_bytes(f"P5\n{w} {h}\n255\n".encode() + pixels.tobytes())
    ox, oy, yaw = costmap.origin
    yaml_path.write_text(f"image: {image_name}\nresolution: {costmap.resolution}\norigin: [{ox}, {oy}, {yaw}]\n"
                         "negate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n")
