"""``auxgps map build --orthophoto``: a prior landmark map from a georeferenced orthophoto.

The orthophoto is read tile by tile at the build's ground sample distance (``--gsd-m``, never finer than the
file), each tile's features detected (:mod:`auxgps.core.prior_map`): ORB with the flight pipeline's own detector
for ``auxgps run``, or SIFT as ``auxgps locate`` uses them. Every keypoint is placed where its pixel lies:
pixel -> the file's CRS (affine) -> WGS84 (PROJ) -> the map's local NED frame, at the height of the height model
(``--dsm``), else of a flat ground: ``--ground-alt-m`` (level), else the ground plane auxgps ortho build wrote
into the file (its height at the centre and its slope), else 0 m of the vertical datum (said so: heights above
home are then taken from where the flight takes off).

The map's origin is the orthophoto's centre on that ground. Its one placement error (``--georef-sigma-m``,
else the one auxgps ortho build wrote into the file, else :data:`DEFAULT_GEOREF_SIGMA_M`) is stated once,
as the map source's, not per landmark.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from auxgps.core.geometry import LocalFrame
from auxgps.core.prior_map import MapSource, PriorMapModel, keep_inside, landmark_columns, tile_grid
from auxgps.errors import MapError
from auxgps.io.orthophoto import TAG_GEOREF_SIGMA, TAG_GROUND_ALT, TAG_GROUND_SLOPE, HeightModel, Orthophoto

#: One-sigma placement error of an orthophoto that does not state its own, m. Public aerial mosaics are commonly
#: specified at a few metres (95 %) and one built from a consumer-GPS survey sits a metre or two off; 2 m is
#: honest for either, and a surveyed orthophoto (ground control points) should say its own with --georef-sigma-m.
DEFAULT_GEOREF_SIGMA_M = 2.0


def _R_ned_image(ortho: Orthophoto, col: float, row: float) -> np.ndarray:
    """R_ned_cam of a nadir camera whose image is the orthophoto's grid at file pixel (col, row): its x axis
    along the columns, z down (grid north is true north only up to the projection's convergence)."""
    step_col, _ = ortho.pixel_steps_ne_m(col, row)
    x = np.array([step_col[0], step_col[1], 0.0]) / np.linalg.norm(step_col)
    z = np.array([0.0, 0.0, 1.0])
    return np.column_stack([x, np.cross(z, x), z])


@dataclass
class PriorMapReport:
    """What ``auxgps map build --orthophoto`` made: the map's columns and frame, its source, and how."""

    columns: dict
    frame: LocalFrame
    source: MapSource
    descriptor: str
    gsd_m: float
    heights: str  # "dsm", "plane (--ground-alt-m)", "plane (the orthophoto's own ground plane)", "datum 0 m"
    tiles: int
    prior: dict = field(default_factory=dict)
    messages: list[str] = field(default_factory=list)

    @property
    def count(self) -> int:
        return len(self.columns["p_ned_m"])


def build_prior_map(ortho_path: Path | str, *, descriptor: str = "orb", pipeline=None, photo_cfg=None,
                    gsd_m: float | None = None, dsm_path: Path | str | None = None, ground_alt_amsl_m: float | None = None,
                    georef_sigma_m: float | None = None, tile_px: int | None = None,
                    progress: Callable[[str], None] | None = None) -> PriorMapReport:
    """A prior map from the orthophoto at ``ortho_path``; ``pipeline`` (a :class:`PipelineConfig`) for ORB maps,
    ``photo_cfg`` (a :class:`PhotoConfig`) for SIFT ones."""
    if descriptor not in ("orb", "sift"):
        raise MapError(f"--descriptor {descriptor!r}: orb (for auxgps run) or sift (for auxgps locate)")
    ortho = Orthophoto(ortho_path)
    dsm = HeightModel(dsm_path) if dsm_path is not None else None
    messages = []
    try:
        build_gsd = ortho.gsd_m if gsd_m is None else float(gsd_m)
        if build_gsd < ortho.gsd_m * 0.999:
            raise MapError(f"--gsd-m {build_gsd:g}: finer than the orthophoto's own {ortho.gsd_m:.4f} m per pixel")
        factor = build_gsd / ortho.gsd_m
        georef = georef_sigma_m if georef_sigma_m is not None else ortho.tag_float(TAG_GEOREF_SIGMA)
        if georef is None:
            georef = DEFAULT_GEOREF_SIGMA_M
            messages.append(f"the orthophoto states no placement error: {georef:g} m one sigma assumed (--georef-sigma-m)")
        # The ground: a height model, else a flat ground at a stated height (level unless the file gives its slope).
        slope_ne = (0.0, 0.0)
        if dsm is not None:
            heights = "dsm"
            centre_alt = float(dsm.alt_amsl_m(np.array([ortho.centre_lat_deg]), np.array([ortho.centre_lon_deg]))[0])
            if not np.isfinite(centre_alt):
                raise MapError(f"--dsm {dsm_path}: no height under the orthophoto's centre (does it cover the same ground?)")
        elif ground_alt_amsl_m is not None:
            heights, centre_alt = "plane (--ground-alt-m)", float(ground_alt_amsl_m)
        elif (tag := ortho.tag_float(TAG_GROUND_ALT)) is not None:
            heights, centre_alt = "plane (the orthophoto's own ground plane)", tag
            slope_ne = ortho.tag_float(TAG_GROUND_SLOPE, 2) or (0.0, 0.0)
        else:
            heights, centre_alt = "datum 0 m", 0.0
            messages.append("no height model and no ground height: landmarks on flat ground at 0 m of the datum; "
                            "heights above home are taken from where the flight takes off (--dsm or --ground-alt-m to say)")
        frame = LocalFrame(ortho.centre_lat_deg, ortho.centre_lon_deg, centre_alt)
        model = PriorMapModel(gsd_m=build_gsd, height_sigma_m=0.5 if dsm is not None else 1.0)

        if descriptor == "orb":
            from auxgps.core.camera import camera_from_config
            from auxgps.core.estimator import prior_map_detector

            detector = prior_map_detector(pipeline)
            camera = camera_from_config(pipeline.camera)
            focal_px = camera.focal_px
            det = pipeline.detector
            tw, th = (tile_px, tile_px) if tile_px else (max(camera.width_px // 2, 64), max(camera.height_px // 2, 48))
            pad = int(np.ceil(det.edge_threshold_px * det.scale_factor ** (det.n_levels - 1))) + 2
        else:
            focal_px = float("nan")
            tw = th = tile_px or max(photo_cfg.max_side_px or 1200, 256)
            pad = 24
        W, H = ortho.build_size_px(factor)
        grid = tile_grid(W, H, tw, th)
        desc_parts, p_parts, scale_parts = [], [], []
        for k, (c0, r0, w, h) in enumerate(grid):
            img, valid = ortho.read(c0 - pad, r0 - pad, w + 2 * pad, h + 2 * pad, factor)
            if valid[pad:pad + h, pad:pad + w].mean() < 0.05:
                continue
            img[~valid] = 0
            if descriptor == "orb":
                f = detector.detect(img, _R_ned_image(ortho, (c0 + w / 2) * factor, (r0 + h / 2) * factor))
                uv, desc = f.uv_px, f.descriptors
                level_scale = det.scale_factor ** f.octave.astype(float)
            else:
                import cv2

                from auxgps.photo.features import detect_sift

                f = detect_sift(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY), 1.0, photo_cfg.n_features, photo_cfg.min_features)
                uv, desc = f.uv_px, f.descriptors
                level_scale = np.maximum(f.size_px / 8.0, 1.0)
            keep = keep_inside(uv, valid, (pad, pad, w, h), margin_px=pad // 2)
            if not np.any(keep):
                continue
            lat, lon = ortho.geodetic_of_build_px(c0 - pad, r0 - pad, uv[keep], factor)
            if dsm is not None:
                alt = dsm.alt_amsl_m(lat, lon)
            else:  # the plane: its height at the centre, risen by its slope over the north/east from there
                ne = frame.to_ned(lat_deg=lat, lon_deg=lon, alt_amsl_m=np.full(len(lat), centre_alt))
                alt = centre_alt + slope_ne[0] * ne[..., 0] + slope_ne[1] * ne[..., 1]
            ok = np.isfinite(alt)
            p_ned = frame.to_ned(lat_deg=lat[ok], lon_deg=lon[ok], alt_amsl_m=alt[ok])
            desc_parts.append(desc[keep][ok])
            p_parts.append(p_ned.reshape(-1, 3))
            scale_parts.append(level_scale[keep][ok])
            if progress is not None and (k % 20 == 0 or k == len(grid) - 1):
                progress(f"tile {k + 1} of {len(grid)}: {sum(len(p) for p in p_parts)} landmarks")
        if not p_parts:
            raise MapError(f"--orthophoto {ortho_path}: no features found (blank, or all outside its coverage mask)")
        columns = landmark_columns(np.vstack(desc_parts), np.vstack(p_parts), np.concatenate(scale_parts), model, focal_px)
        source = MapSource("orthophoto", Path(ortho_path).name, float(georef))
        prior = {"orthophoto": str(ortho_path), "crs": ortho.crs.to_string(), "file_gsd_m": ortho.gsd_m, "gsd_m": build_gsd,
                 "heights": heights, "ground_slope_ne": list(slope_ne), "dsm": None if dsm_path is None else str(dsm_path), "descriptor": descriptor,
                 "focal_px": None if descriptor != "orb" else focal_px, "georef_sigma_h_m": float(georef)}
        return PriorMapReport(columns, frame, source, descriptor, build_gsd, heights, len(grid), prior, messages)
    finally:
        ortho.close()
        if dsm is not None:
            dsm.close()
