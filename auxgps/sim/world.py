"""Simulated worlds: a ground (flat colour, texture, or a georeferenced orthophoto with an optional height
model), featureless patches lying on it and cubes standing on it, read from YAML.

World file keys (all lengths in metres, angles in degrees, colours BGR 0-255 or a name)::

    origin: {lat_deg: 47.3977, lon_deg: 8.5456, alt_amsl_m: 488.0}   # the local frame's anchor, on the ground
    ground: {color: [128, 128, 128]}          # or {texture: PATH, m_per_px: 0.05}; PATH relative to the file
                                              # or {orthophoto: PATH.tif} and optionally dsm: PATH.tif
    cubes:
      - {east_m: 1.0, north_m: 2.0, size_m: 0.5, color: red, yaw_deg: 0}
    patches:                                  # optional: flat polygons of one colour on the ground (down = 0)
      - {name: lake, color: [90, 60, 30], corners_m: [[4, -3], [9, -1], [7, 4], [3, 2]]}   # [north_m, east_m] each
    description: free text (optional)

An ``orthophoto`` is a georeferenced GeoTIFF in any CRS (1, 3 or 4 bands of uint8), placed in the local NED
frame by reprojection (:mod:`auxgps.io.georaster`); ground off it is black. The world origin must lie on it.
Without a ``dsm`` the ground is the plane ``down = 0`` (the origin's tangent plane), as for the other grounds.

A ``dsm`` is a height model GeoTIFF in any CRS, band 1 in metres, in the same vertical datum as the origin's
``alt_amsl_m`` (both are taken as the height pymap3d converts: a DSM in metres above sea level goes with an
origin altitude above sea level). Its surface point at a latitude and longitude is the point of that geodetic
height; in NED, the ground under (north, east) is at ``down = h0 - h_dsm``, where ``h0`` is the geodetic height
of the tangent-plane point (north, east, 0) (so a DSM equal to the origin's altitude everywhere follows the
ellipsoid, 8 cm below the tangent plane 1 km out). Off the DSM and at its no-data the height is the origin's
altitude. Cubes stand on the DSM's height at their centre.

A ``patch`` is a simple polygon (at least 3 corners, in order) of one flat colour, unshaded: water, a bare field, a
uniform roof, the ground a camera finds no features on. It lies on the plane ``down = 0``, over the ground and under
the cubes; where patches overlap, the later one is on top. Patches go with flat ground only, not with a ``dsm``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass as std_dataclass
from pathlib import Path
from typing import Annotated, Union

import cv2
import numpy as np
from pydantic import Field, FiniteFloat, field_validator, model_validator
from pydantic.dataclasses import dataclass

from auxgps.config import _STRICT, parse_as, read_yaml
from auxgps.core.geometry import LocalFrame
from auxgps.errors import ConfigError
from auxgps.io.georaster import GeoRaster
from auxgps.sim.geoground import OFF_RASTER_BGR

COLOR_NAMES_BGR: dict[str, tuple[int, int, int]] = {
    "black": (20, 20, 20),
    "white": (235, 235, 235),
    "red": (40, 40, 200),
    "green": (40, 170, 40),
    "blue": (200, 70, 30),
    "yellow": (30, 210, 220),
    "orange": (20, 120, 240),
    "purple": (150, 40, 130),
    "grey": (128, 128, 128),
    "gray": (128, 128, 128),
}

ColorValue = Union[str, Annotated[list[Annotated[int, Field(ge=0, le=255)]], Field(min_length=3, max_length=3)]]


def _color_to_bgr(value: ColorValue) -> tuple[int, int, int]:
    if isinstance(value, str):
        if value.lower() not in COLOR_NAMES_BGR:
            raise ValueError(f"unknown colour name {value!r}; known: {', '.join(sorted(COLOR_NAMES_BGR))}")
        return COLOR_NAMES_BGR[value.lower()]
    return tuple(int(v) for v in value)  # type: ignore[return-value]


@dataclass(config=_STRICT, frozen=True)
class OriginSpec:
    lat_deg: Annotated[float, Field(ge=-90, le=90)]
    lon_deg: Annotated[float, Field(ge=-180, le=180)]
    alt_amsl_m: Annotated[float, Field(ge=-500, le=9000)]


@dataclass(config=_STRICT, frozen=True)
class GroundSpec:
    color: ColorValue | None = None
    texture: str | None = None
    m_per_px: Annotated[float, Field(gt=0)] | None = None
    orthophoto: str | None = None
    dsm: str | None = None

    @field_validator("color")
    @classmethod
    def _check_color(cls, v):
        if v is not None:
            _color_to_bgr(v)
        return v

    @model_validator(mode="after")
    def _one_kind(self) -> "GroundSpec":
        if sum(k is not None for k in (self.color, self.texture, self.orthophoto)) != 1:
            raise ValueError("give exactly one of color, texture or orthophoto")
        if self.texture is not None and self.m_per_px is None:
            raise ValueError("texture needs m_per_px")
        if self.texture is None and self.m_per_px is not None:
            raise ValueError("m_per_px goes with texture only (an orthophoto carries its own georeference)")
        if self.dsm is not None and self.orthophoto is None:
            raise ValueError("dsm goes with orthophoto only")
        return self


@dataclass(config=_STRICT, frozen=True)
class CubeSpec:
    east_m: float
    north_m: float
    size_m: Annotated[float, Field(gt=0, le=100)]
    color: ColorValue = "white"
    yaw_deg: Annotated[float, Field(ge=-360, le=360)] = 0.0

    @field_validator("color")
    @classmethod
    def _check_color(cls, v):
        _color_to_bgr(v)
        return v


@dataclass(config=_STRICT, frozen=True)
class PatchSpec:
    corners_m: Annotated[list[Annotated[list[FiniteFloat], Field(min_length=2, max_length=2)]], Field(min_length=3)]
    color: ColorValue
    name: str = ""

    @field_validator("color")
    @classmethod
    def _check_color(cls, v):
        _color_to_bgr(v)
        return v


@dataclass(config=_STRICT, frozen=True)
class WorldSpec:
    origin: OriginSpec
    ground: GroundSpec = Field(default_factory=lambda: GroundSpec(color=[128, 128, 128]))
    cubes: list[CubeSpec] = Field(default_factory=list)
    patches: list[PatchSpec] = Field(default_factory=list)
    description: str = ""

    @model_validator(mode="after")
    def _patches_on_flat_ground(self) -> "WorldSpec":
        if self.patches and self.ground.dsm is not None:
            raise ValueError("patches lie on flat ground (down = 0), not with ground.dsm: its relief would hide them wrongly")
        return self


@std_dataclass(frozen=True)
class Cube:
    """A cube standing on the ground. ``center_ne_m`` (2,), ``size_m``, ``yaw_rad``, ``color_bgr``;
    ``base_down_m`` the down of its bottom face (0 on flat ground; the ground's height at its centre over a DSM)."""

    center_ne_m: np.ndarray
    size_m: float
    yaw_rad: float
    color_bgr: tuple[int, int, int]
    base_down_m: float = 0.0

    def vertices_ned(self) -> np.ndarray:
        """(8, 3) corners in NED: the 4 bottom ones (down = base) then the 4 top ones (down = base - size)."""
        h = self.size_m / 2.0
        c, s = np.cos(self.yaw_rad), np.sin(self.yaw_rad)
        local = np.array([[-h, -h], [h, -h], [h, h], [-h, h]])
        ne = local @ np.array([[c, s], [-s, c]]) + self.center_ne_m
        bottom = np.column_stack([ne, np.full(4, self.base_down_m)])
        top = np.column_stack([ne, np.full(4, self.base_down_m - self.size_m)])
        return np.vstack([bottom, top])

    def faces(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """The 5 visible-able faces (no bottom) as ((4, 3) corners, (3,) outward unit normal), NED."""
        v = self.vertices_ned()
        top = (v[[4, 5, 6, 7]], np.array([0.0, 0.0, -1.0]))
        faces = [top]
        for i in range(4):
            j = (i + 1) % 4
            quad = v[[i, j, j + 4, i + 4]]
            mid = quad.mean(axis=0)
            n = mid - np.array([*self.center_ne_m, mid[2]])
            faces.append((quad, n / np.linalg.norm(n)))
        return faces


@std_dataclass(frozen=True)
class Patch:
    """A featureless polygon of one flat colour lying on the ground (down = 0). ``corners_ne_m`` (K, 2) float64,
    north, east, m, in order; ``color_bgr``; ``name`` free text ("lake"), possibly empty."""

    name: str
    corners_ne_m: np.ndarray
    color_bgr: tuple[int, int, int]


@std_dataclass(frozen=True)
class World:
    """A loaded world: its local frame, ground, patches and cubes."""

    frame: LocalFrame
    cubes: tuple[Cube, ...]
    ground_color_bgr: tuple[int, int, int] | None
    ground_texture_bgr: np.ndarray | None
    ground_m_per_px: float | None
    source: str = ""
    description: str = ""
    ground_orthophoto: GeoRaster | None = None
    ground_dsm: GeoRaster | None = None
    patches: tuple[Patch, ...] = ()

    def patch_at(self, p_ne_m: np.ndarray) -> np.ndarray:
        """(N, 2) north, east, m -> (N,) int: the index in :attr:`patches` of the patch on top at each point (the
        last one that contains it), -1 for none. A point on a patch's edge may fall either way."""
        from matplotlib.path import Path as PolygonPath  # matplotlib only where patches are asked about

        p = np.asarray(p_ne_m, float).reshape(-1, 2)
        index = np.full(len(p), -1, int)
        for i, patch in enumerate(self.patches):
            index[PolygonPath(patch.corners_ne_m).contains_points(p)] = i
        return index

    def ground_down_m(self, p_ne_m: np.ndarray) -> np.ndarray:
        """(..., 2) north, east, m -> (...) the down of the ground there, m: 0 without a DSM, else from the DSM
        (bilinear at full resolution; the origin's altitude off it). For a few points, not per pixel."""
        p = np.asarray(p_ne_m, float)
        if self.ground_dsm is None:
            return np.zeros(p.shape[:-1])
        p_ned = np.concatenate([p, np.zeros(p.shape[:-1] + (1,))], axis=-1)
        x, y, h0_m = self.ground_dsm.crs_from_ned(self.frame, p_ned)
        h_m = self.ground_dsm.sample(x, y)
        return h0_m - np.where(np.isfinite(h_m), h_m, self.frame.alt_amsl_m)

    def all_vertices_ned(self) -> np.ndarray:
        """(8 * n_cubes, 3) every cube corner, NED."""
        if not self.cubes:
            return np.zeros((0, 3))
        return np.vstack([c.vertices_ned() for c in self.cubes])


def _relative(path_text: str, base_dir: Path | None) -> Path:
    path = Path(path_text)
    return base_dir / path if not path.is_absolute() and base_dir is not None else path


def _georaster(key: str, path_text: str, kind: str, frame: LocalFrame, source: str, base_dir: Path | None) -> GeoRaster:
    """Open ``ground.<key>`` and check that the world origin lies on it."""
    raster = GeoRaster(_relative(path_text, base_dir), f"{source}: ground.{key}", kind,
                       fill_bgr=OFF_RASTER_BGR if kind == "orthophoto" else None)
    x, y, _ = raster.crs_from_ned(frame, np.zeros(3))
    if not np.all(np.isfinite([x, y])) or not raster.contains(float(x), float(y)):
        b = raster.bounds
        raise ConfigError(
            f"{source}: ground.{key}: the world origin ({frame.lat_deg}, {frame.lon_deg}) is outside {raster.path} "
            f"(at {float(x):.2f}, {float(y):.2f} in its CRS {raster.crs.to_string()}; the raster spans x {b.left:.2f} to "
            f"{b.right:.2f}, y {b.bottom:.2f} to {b.top:.2f})"
        )
    return raster


def world_from_spec(spec: WorldSpec, source: str = "", base_dir: Path | None = None) -> World:
    texture = None
    if spec.ground.texture is not None:
        path = _relative(spec.ground.texture, base_dir)
        texture = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if texture is None:
            raise ConfigError(f"{source}: ground.texture: cannot read image {path}")
    frame = LocalFrame(spec.origin.lat_deg, spec.origin.lon_deg, spec.origin.alt_amsl_m)
    ortho = dsm = None
    if spec.ground.orthophoto is not None:
        ortho = _georaster("orthophoto", spec.ground.orthophoto, "orthophoto", frame, source, base_dir)
    if spec.ground.dsm is not None:
        dsm = _georaster("dsm", spec.ground.dsm, "dsm", frame, source, base_dir)
        dsm.heights_range_m()  # a DSM of no-data only is refused here, not at the first frame
    world = World(
        frame=frame,
        cubes=(),
        ground_color_bgr=_color_to_bgr(spec.ground.color) if spec.ground.color is not None else None,
        ground_texture_bgr=texture,
        ground_m_per_px=spec.ground.m_per_px,
        source=source,
        description=spec.description,
        ground_orthophoto=ortho,
        ground_dsm=dsm,
        patches=tuple(Patch(p.name, np.array(p.corners_m, float), _color_to_bgr(p.color)) for p in spec.patches),
    )
    centers_ne_m = np.array([[c.north_m, c.east_m] for c in spec.cubes], float).reshape(-1, 2)
    base_down_m = world.ground_down_m(centers_ne_m)
    cubes = tuple(
        Cube(centers_ne_m[i].copy(), float(c.size_m), float(np.deg2rad(c.yaw_deg)), _color_to_bgr(c.color), float(base_down_m[i]))
        for i, c in enumerate(spec.cubes)
    )
    return dataclasses.replace(world, cubes=cubes)


def load_world(path: Path | str) -> World:
    """Read a world YAML file, or one of auxgps's worlds by name (:func:`auxgps.resources.world_path`). Any problem
    is a :class:`ConfigError` naming the file and the key."""
    from auxgps.resources import world_path

    path = world_path(path)
    spec = parse_as(WorldSpec, read_yaml(path), path)
    return world_from_spec(spec, source=str(path), base_dir=path.parent)
