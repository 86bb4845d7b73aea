"""A simulated camera: renders a :class:`~auxgps.sim.world.World` exactly as a :class:`PinholeCamera` sees it.

The ground is a flat colour, a texture warped by the ground-plane homography, or a georeferenced orthophoto
reprojected into the view (:class:`~auxgps.sim.geoground.GeoGround`), flat or over a height model; featureless
patches are painted over the flat ground in their own colours, unshaded; cube faces are filled as anti-aliased
polygons with per-face Lambertian shading, resolved per pixel with a depth buffer. Lens distortion, when the
camera has any, is applied last by remapping the ideal image. The renderer also gives,
for evaluation only, the true 3D point behind any pixel.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from auxgps.core.camera import CameraPose, PinholeCamera
from auxgps.sim.geoground import GeoGround
from auxgps.sim.world import World

#: Unit vectors from a surface towards the two lights (NED): a sun high in the south-east, a dim sky fill.
_SUN_NED = np.array([-0.35, 0.45, -0.82]) / np.linalg.norm([-0.35, 0.45, -0.82])
_FILL_NED = np.array([0.6, -0.2, -0.77]) / np.linalg.norm([0.6, -0.2, -0.77])


def clip_polygon(p: np.ndarray, normal: np.ndarray, offset: float) -> np.ndarray:
    """The part of the polygon ``p`` (K, 3), corners in order, where ``normal @ p >= offset``: (K', 3), K' 0 when
    none of it is (Sutherland-Hodgman against one plane)."""
    s = p @ normal - offset
    s_next, p_next = np.roll(s, -1), np.roll(p, -1, axis=0)
    inside = s >= 0
    with np.errstate(divide="ignore", invalid="ignore"):
        crossing = p + (p_next - p) * (s / (s - s_next))[:, None]
    # Each edge gives its start when that is inside, then the point where it crosses the plane, if it does.
    return np.stack([p, crossing], axis=1)[np.stack([inside, inside != (s_next >= 0)], axis=1)]


def face_shade(normal_ned: np.ndarray) -> float:
    """Brightness factor of a face with outward unit normal ``normal_ned``: ambient + sun + sky fill."""
    return float(0.30 + 0.55 * max(0.0, normal_ned @ _SUN_NED) + 0.20 * max(0.0, normal_ned @ _FILL_NED))


#: Where the sun is, for the glare, unless a configuration says otherwise: about where the shading's sun is.
SUN_AZIMUTH_DEG = 128.0
SUN_ELEVATION_DEG = 55.0


def sun_dir_ned(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """(3,) unit vector from the ground towards the sun (NED): azimuth from north towards east, elevation above
    the horizon, degrees."""
    az, el = np.deg2rad(azimuth_deg), np.deg2rad(elevation_deg)
    return np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), -np.sin(el)])


@dataclass(frozen=True)
class ImageEffects:
    """What the simulated camera does to one frame after rendering. The defaults change nothing.

    Whole-run effects: ``noise_sigma`` (white Gaussian noise, grey levels), ``blur_sigma_px`` (Gaussian defocus,
    px), ``exposure_gain``. An appearance shift (the camera's auto-exposure and white balance having moved):
    ``shift_gain``, ``shift_gain_bgr`` (B, G, R), ``shift_gamma``. Sun glare: a soft saturating blob where a flat
    ground reflects the sun (``sun_dir_ned``) towards the camera, ``glare_strength`` its peak as a share of full
    scale (1 saturates its core), ``glare_core_frac`` its core's radius and ``glare_falloff_frac`` the one sigma
    of its soft edge (both shares of the image width), ``glare_haze`` a veil over the whole frame (the share of full
    scale every pixel is blended towards). Motion blur: the ground's motion in the image during
    ``exposure_time_s``. Sensor noise: shot noise of variance ``shot_noise_dn`` (grey levels squared per grey
    level of signal) and read noise of one sigma ``read_noise_dn`` (grey levels).
    """

    noise_sigma: float = 0.0
    blur_sigma_px: float = 0.0
    exposure_gain: float = 1.0
    shift_gain: float = 1.0
    shift_gain_bgr: tuple[float, float, float] = (1.0, 1.0, 1.0)
    shift_gamma: float = 1.0
    glare_strength: float = 0.0
    glare_core_frac: float = 0.05
    glare_falloff_frac: float = 0.08
    glare_haze: float = 0.0
    sun_dir_ned: tuple[float, float, float] = tuple(float(x) for x in sun_dir_ned(SUN_AZIMUTH_DEG, SUN_ELEVATION_DEG))
    exposure_time_s: float = 0.0
    shot_noise_dn: float = 0.0
    read_noise_dn: float = 0.0

    @property
    def has_shift(self) -> bool:
        return self.shift_gain != 1.0 or tuple(self.shift_gain_bgr) != (1.0, 1.0, 1.0) or self.shift_gamma != 1.0

    @property
    def has_glare(self) -> bool:
        return self.glare_strength > 0 or self.glare_haze > 0

    @property
    def is_identity(self) -> bool:
        return (self.exposure_gain == 1.0 and self.blur_sigma_px <= 0 and self.noise_sigma <= 0 and not self.has_shift
                and not self.has_glare and self.exposure_time_s <= 0 and self.shot_noise_dn <= 0 and self.read_noise_dn <= 0)


@dataclass
class RenderedFrame:
    """A rendered image and, for evaluation only, the depth behind every pixel.

    Attributes
    ----------
    image_bgr : (H, W, 3) uint8
    pose : the true camera pose it was rendered from
    depth_m : (H, W) float32, z-depth along the optical axis of the nearest surface (m)
    """

    image_bgr: np.ndarray
    pose: CameraPose
    depth_m: np.ndarray
    camera: PinholeCamera
    visible_vertices_ned: np.ndarray = field(repr=False)
    visible_vertices_px: np.ndarray = field(repr=False)

    def points_ned(self) -> np.ndarray:
        """(H, W, 3) float64: the true NED point behind every pixel centre."""
        H, W = self.depth_m.shape
        u, v = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
        xy = self.camera.pixels_to_normalized(np.column_stack([u.ravel(), v.ravel()])).reshape(H, W, 2)
        z = self.depth_m.astype(float)[..., None]
        p_cam = np.concatenate([xy * z, z], axis=2)
        return p_cam @ self.pose.R_ned_cam.T + self.pose.p_cam_in_ned_m

    def points_at(self, uv_px: np.ndarray) -> np.ndarray:
        """(N, 2) pixels -> (N, 3) true NED points behind their (rounded) pixel centres."""
        uv = np.atleast_2d(np.asarray(uv_px, float))
        col = np.clip(np.rint(uv[:, 0]).astype(int), 0, self.depth_m.shape[1] - 1)
        row = np.clip(np.rint(uv[:, 1]).astype(int), 0, self.depth_m.shape[0] - 1)
        z = self.depth_m[row, col].astype(float)
        xy = self.camera.pixels_to_normalized(np.column_stack([col, row]).astype(float))
        p_cam = np.column_stack([xy * z[:, None], z])
        return p_cam @ self.pose.R_ned_cam.T + self.pose.p_cam_in_ned_m

    def true_points_at(self, uv_px: np.ndarray, snap_px: float = 2.5) -> np.ndarray:
        """The true 3D point a point feature at ``uv_px`` stands for, (N, 3) NED.

        A corner feature lies on a cube vertex, where the pixel itself may show the ground behind the
        silhouette; so a feature within ``snap_px`` of a visible vertex's projection is that vertex, and any
        other feature is the surface point behind its pixel.
        """
        uv = np.atleast_2d(np.asarray(uv_px, float))
        points = self.points_at(uv)
        if len(self.visible_vertices_px):
            d = np.linalg.norm(uv[:, None, :] - self.visible_vertices_px[None, :, :], axis=2)
            nearest = np.argmin(d, axis=1)
            snap = d[np.arange(len(uv)), nearest] <= snap_px
            points[snap] = self.visible_vertices_ned[nearest[snap]]
        return points


class Renderer:
    """Renders one world through one camera. Build once, call :meth:`render` per pose."""

    def __init__(self, world: World, camera: PinholeCamera) -> None:
        self.world = world
        self.camera = camera
        W, H = camera.width_px, camera.height_px
        # Rendering happens in an ideal (undistorted) pinhole image with the same K; distortion is a remap after.
        self._K = camera.K
        Kinv = np.linalg.inv(camera.K)
        u = np.arange(W, dtype=np.float32)
        v = np.arange(H, dtype=np.float32)
        self._xn = ((u - camera.K[0, 2]) * Kinv[0, 0]).astype(np.float32)  # (W,)
        self._yn = ((v - camera.K[1, 2]) * Kinv[1, 1]).astype(np.float32)  # (H,)
        self._cubes = [
            (cube, [(quad, normal, np.array(cube.color_bgr, float) * face_shade(normal)) for quad, normal in cube.faces()])
            for cube in world.cubes
        ]
        self._vertices = world.all_vertices_ned()
        self._patches = [(np.column_stack([p.corners_ne_m, np.zeros(len(p.corners_ne_m))]), p.color_bgr)
                         for p in world.patches]  # (corners (K, 3) NED, colour)
        # A patch is clipped in the camera frame before it is projected: in front of the lens (corners behind it would
        # fold over), and within a guard band of one image size around the image (fillPoly's fixed point can overflow).
        # Planes as (normal, offset), keeping normal @ p_cam >= offset.
        x_lo, x_hi = (-W - camera.K[0, 2]) / camera.K[0, 0], (2 * W - camera.K[0, 2]) / camera.K[0, 0]
        y_lo, y_hi = (-H - camera.K[1, 2]) / camera.K[1, 1], (2 * H - camera.K[1, 2]) / camera.K[1, 1]
        self._patch_clip_planes_cam = [(np.array([0.0, 0.0, 1.0]), self._NEAR_M)] + [
            (np.array(n), 0.0) for n in ([1.0, 0.0, -x_lo], [-1.0, 0.0, x_hi], [0.0, 1.0, -y_lo], [0.0, -1.0, y_hi])
        ]
        # A plain ground is the same image in every frame: made once, copied per frame.
        self._plain_ground = None if world.ground_color_bgr is None else np.full((H, W, 3), world.ground_color_bgr, np.uint8)
        self._geo = GeoGround(world, camera, self._xn, self._yn) if world.ground_orthophoto is not None else None
        self._distort_maps = self._make_distortion_maps() if camera.has_distortion else None

    def _make_distortion_maps(self) -> tuple[np.ndarray, np.ndarray]:
        """For each pixel of the distorted image, where it comes from in the ideal image."""
        W, H = self.camera.width_px, self.camera.height_px
        u, v = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
        xy = self.camera.pixels_to_normalized(np.column_stack([u.ravel(), v.ravel()]))
        src = xy * np.array([self._K[0, 0], self._K[1, 1]]) + self._K[:2, 2]
        return src[:, 0].reshape(H, W).astype(np.float32), src[:, 1].reshape(H, W).astype(np.float32)

    def _ground(self, pose: CameraPose) -> np.ndarray:
        W, H = self.camera.width_px, self.camera.height_px
        world = self.world
        if self._plain_ground is not None:
            return self._plain_ground.copy()
        if self._geo is not None:
            return self._geo.flat_image(pose)
        R_cam_ned = pose.R_ned_cam.T
        H_img_ground = self._K @ np.column_stack([R_cam_ned[:, 0], R_cam_ned[:, 1], -R_cam_ned @ pose.p_cam_in_ned_m])
        th, tw = world.ground_texture_bgr.shape[:2]
        s = world.ground_m_per_px
        A = np.array([[0.0, -s, (th / 2.0) * s], [s, 0.0, -(tw / 2.0) * s], [0.0, 0.0, 1.0]])
        return cv2.warpPerspective(
            world.ground_texture_bgr, H_img_ground @ A, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101
        )

    def _ground_depth(self, pose: CameraPose) -> np.ndarray:
        """(H, W) float32 z-depth of the ground plane (down = 0) behind every ideal pixel; inf above the horizon."""
        r = pose.R_ned_cam[2].astype(np.float32)
        ray_down = r[0] * self._xn[None, :] + r[1] * self._yn[:, None] + r[2]
        with np.errstate(divide="ignore"):
            z = np.float32(-pose.p_cam_in_ned_m[2]) / ray_down
        z[~(z > 0)] = np.inf
        return z

    def render(
        self, pose: CameraPose, effects: ImageEffects | None = None, rng: np.random.Generator | None = None,
        v_ned_m_s: np.ndarray | None = None,
    ) -> RenderedFrame:
        """Render the view from ``pose``. ``rng`` drives the sensor noise, if any; ``v_ned_m_s`` (3,), the camera's
        true velocity, the motion blur (none without it). A lens within :data:`MIN_LENS_HEIGHT_M` of the ground (a
        vehicle standing on it) sees nothing: a black frame, depth 0."""
        c = pose.p_cam_in_ned_m
        ground_down_m = float(self.world.ground_down_m(c[:2]))  # under the lens (a DSM lookup: once a frame)
        if c[2] > ground_down_m - self.MIN_LENS_HEIGHT_M:
            H, W = self.camera.height_px, self.camera.width_px
            return RenderedFrame(np.zeros((H, W, 3), np.uint8), pose, np.zeros((H, W), np.float32), self.camera,
                                 np.zeros((0, 3)), np.zeros((0, 2)))
        if self._geo is not None and self._geo.dsm is not None:
            # Relief: the terrain is in the depth buffer before the cubes, so that it can hide them.
            image, ground_depth = self._geo.relief(pose)
            zbuf = ground_depth.copy()
        else:
            image, ground_depth = self._ground(pose), None
            zbuf = np.full(image.shape[:2], np.inf, np.float32)
        for corners_ned, color_bgr in self._patches:  # on the ground, under the cubes
            self._draw_patch(image, pose, corners_ned, color_bgr)
        c = pose.p_cam_in_ned_m
        for cube, faces in sorted(self._cubes, key=lambda cf: -np.linalg.norm(cf[0].vertices_ned().mean(0) - c)):
            front = [f for f in faces if f[1] @ (f[0].mean(axis=0) - c) < 0]  # faces turned towards the camera
            self._draw_cube(image, zbuf, pose, front)
        depth = np.minimum(zbuf, self._ground_depth(pose) if ground_depth is None else ground_depth)
        if self._distort_maps is not None:
            mx, my = self._distort_maps
            image = cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            depth = cv2.remap(depth, mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
        if effects is not None and not effects.is_identity:
            blur_px = None
            if effects.exposure_time_s > 0 and v_ned_m_s is not None:
                height_m = ground_down_m - float(c[2])
                blur_px = ground_motion_px(self.camera, pose, v_ned_m_s, height_m, effects.exposure_time_s)
            glint_px = sun_glint_px(self.camera, pose, np.asarray(effects.sun_dir_ned)) if effects.glare_strength > 0 else None
            image = apply_effects(image, effects, rng, motion_px=blur_px, glint_px=glint_px)
        vis_ned, vis_px = self._visible_vertices(pose, depth)
        return RenderedFrame(image, pose, depth, self.camera, vis_ned, vis_px)

    #: Supersampling factor for the anti-aliased cube edges.
    _SS = 4
    #: Below this height above the ground the lens sees nothing (the ground-plane homography degenerates there).
    MIN_LENS_HEIGHT_M = 0.05
    #: A patch is clipped to this z-depth in front of the lens, m.
    _NEAR_M = 1e-3

    def _draw_patch(self, image, pose, corners_ned, color_bgr) -> None:
        """Fill one patch, corners (K, 3) NED on the ground plane, in its flat colour with an anti-aliased edge.

        OpenCV's anti-aliased fill strokes the outline over the filled polygon, so the patch comes out about 2/3 px
        wider on every side than its true outline (exact area coverage, as the cubes have, costs about 12 ms for a
        patch filling a 1280 x 720 frame, against 0.4 ms)."""
        p_cam = pose.ned_to_cam(corners_ned)
        for normal, offset in self._patch_clip_planes_cam:
            p_cam = clip_polygon(p_cam, normal, offset)
        if len(p_cam) < 3:
            return
        uv = p_cam[:, :2] / p_cam[:, 2:3] * [self._K[0, 0], self._K[1, 1]] + self._K[:2, 2]
        cv2.fillPoly(image, [np.rint(uv * 16).astype(np.int32)], color_bgr, lineType=cv2.LINE_AA, shift=4)

    def _draw_cube(self, image, zbuf, pose, faces) -> None:
        """Composite one convex cube: supersampled coverage and colour, per-pixel depth test against ``zbuf``."""
        H, W = zbuf.shape
        fxy = np.array([self._K[0, 0], self._K[1, 1]])
        polys = []
        for quad, normal, color in faces:
            p_cam = pose.ned_to_cam(quad)
            if np.any(p_cam[:, 2] <= 1e-3):
                return  # a cube reaching the camera plane is not drawn (the camera flies above the cubes)
            polys.append((p_cam[:, :2] / p_cam[:, 2:3] * fxy + self._K[:2, 2], quad, normal, color))
        if not polys:
            return
        uv_all = np.vstack([p[0] for p in polys])
        x0 = max(int(np.floor(uv_all[:, 0].min())) - 1, 0)
        y0 = max(int(np.floor(uv_all[:, 1].min())) - 1, 0)
        x1 = min(int(np.ceil(uv_all[:, 0].max())) + 2, W)
        y1 = min(int(np.ceil(uv_all[:, 1].max())) + 2, H)
        if x1 <= x0 or y1 <= y0:
            return
        ss = self._SS
        h, w = y1 - y0, x1 - x0
        label = np.zeros((h * ss, w * ss), np.uint8)  # which face covers each supersample (0: none)
        z = np.full((h, w), -np.inf, np.float32)
        for k, (uv, quad, normal, color) in enumerate(polys, start=1):
            # Pixel centres of the supersampled grid sit at (i + 0.5) / ss - 0.5 in full-size pixels.
            pts = np.rint(((uv - [x0, y0]) * ss + (ss - 1) / 2.0) * 16).astype(np.int32)
            cv2.fillConvexPoly(label, pts, k, lineType=cv2.LINE_8, shift=4)
            # Depth of the face plane at each pixel centre; the cube's surface is the farthest front plane.
            nR = normal @ pose.R_ned_cam
            denom = nR[0] * self._xn[None, x0:x1] + nR[1] * self._yn[y0:y1, None] + nR[2]
            with np.errstate(divide="ignore", invalid="ignore"):
                zf = (normal @ (quad[0] - pose.p_cam_in_ned_m)) / denom
            z = np.maximum(z, np.where(zf > 0, zf, -np.inf).astype(np.float32))
        # Each face's coverage of each pixel (its share of the pixel's supersamples), and the premultiplied colour.
        # A supersample weighs ss^2, so that the area average of a pixel's ss x ss block is the count, exactly.
        colour = np.zeros((h, w, 3), np.float32)
        alpha = np.zeros((h, w), np.float32)
        for k, (_, _, _, color) in enumerate(polys, start=1):
            weight = np.where(label == k, np.uint8(ss * ss), np.uint8(0))
            cover = cv2.resize(weight, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32) / ss**2
            colour += cover[..., None] * np.asarray(color, np.float32)
            alpha += cover
        zpatch = zbuf[y0:y1, x0:x1]
        closer = (z > 0) & (z <= zpatch + 1e-3)
        a = alpha * closer
        patch = image[y0:y1, x0:x1].astype(np.float32)
        patch = colour * closer[..., None] + (1.0 - a[..., None]) * patch
        image[y0:y1, x0:x1] = np.clip(np.rint(patch), 0, 255).astype(np.uint8)
        zbuf[y0:y1, x0:x1] = np.where((alpha >= 0.5) & closer, z, zpatch)

    def _visible_vertices(self, pose: CameraPose, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if len(self._vertices) == 0:
            return np.zeros((0, 3)), np.zeros((0, 2))
        p_cam = pose.ned_to_cam(self._vertices)
        uv, in_front = self.camera.project_cam(p_cam)
        inside = in_front & self.camera.in_image(np.nan_to_num(uv, nan=-1.0))
        col = np.clip(np.rint(np.nan_to_num(uv[:, 0])).astype(int), 0, depth.shape[1] - 1)
        row = np.clip(np.rint(np.nan_to_num(uv[:, 1])).astype(int), 0, depth.shape[0] - 1)
        # A vertex is hidden when something is clearly in front of it at its own pixel.
        unoccluded = p_cam[:, 2] <= depth[row, col] + 0.05 + 0.01 * p_cam[:, 2]
        keep = inside & unoccluded
        return self._vertices[keep], uv[keep]


def ground_motion_px(camera: PinholeCamera, pose: CameraPose, v_ned_m_s: np.ndarray, height_m: float,
                     exposure_s: float) -> np.ndarray:
    """(2,) px (x right, y down): how far the ground below moves in the image during one exposure.

    Its length is the ground speed across the optical axis times ``exposure_s`` over the ground sample distance
    (``height_m`` / focal length px); its direction, the camera's motion projected into the image, reversed (the
    ground moves the other way). Rotation during the exposure and the radial blur of a climb or descent are left out.
    """
    v_cam = pose.R_ned_cam.T @ np.asarray(v_ned_m_s, float)
    gsd_m = max(float(height_m), 1e-3) / camera.focal_px
    return -v_cam[:2] * exposure_s / gsd_m


def sun_glint_px(camera: PinholeCamera, pose: CameraPose, sun_dir_ned: np.ndarray) -> np.ndarray | None:
    """(2,) px: where a flat ground mirrors the sun (unit vector towards it, NED) into the camera; None when that
    direction is behind the camera. Fixed relative to the sun's direction, it turns in the image as the vehicle
    turns, and travels over the ground with it."""
    d_ned = np.asarray(sun_dir_ned, float) * np.array([1.0, 1.0, -1.0])  # the mirror of the sun in the ground plane
    uv, in_front = camera.project_cam((pose.R_ned_cam.T @ d_ned)[None, :])
    return uv[0] if in_front[0] else None


def line_kernel(motion_px: np.ndarray) -> np.ndarray:
    """(K, K) float32, sum 1: a straight segment of length ``|motion_px|`` px along ``motion_px``, centred,
    anti-aliased (sampled every 1/8 px and spread bilinearly)."""
    d = np.asarray(motion_px, float)
    length = float(np.hypot(*d))
    half = int(np.ceil(length / 2.0)) + 1
    k = np.zeros((2 * half + 1, 2 * half + 1), np.float64)
    n = max(2, int(np.ceil(length * 8)) + 1)
    pts = half + np.linspace(-0.5, 0.5, n)[:, None] * d[None, :]
    x0, y0 = np.floor(pts[:, 0]).astype(int), np.floor(pts[:, 1]).astype(int)
    fx, fy = pts[:, 0] - x0, pts[:, 1] - y0
    for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        np.add.at(k, (y0 + dy, x0 + dx), w)
    return (k / k.sum()).astype(np.float32)


def glare_light(shape_hw: tuple[int, int], glint_px: np.ndarray, strength: float, core_frac: float,
                falloff_frac: float) -> np.ndarray:
    """(H, W) float32 grey levels: the sun's glare about ``glint_px``: ``strength`` x 255 inside a core of
    radius ``core_frac`` x width, falling off as a Gaussian of one sigma ``falloff_frac`` x width beyond it."""
    H, W = shape_hw
    u = np.arange(W, dtype=np.float32) - np.float32(glint_px[0])
    v = np.arange(H, dtype=np.float32) - np.float32(glint_px[1])
    r = np.sqrt(u[None, :] ** 2 + v[:, None] ** 2)
    beyond = np.maximum(r - np.float32(core_frac * W), 0.0)
    sigma = max(falloff_frac * W, 1e-3)
    return (np.float32(255.0 * strength) * np.exp(-0.5 * (beyond / np.float32(sigma)) ** 2)).astype(np.float32)


def _add_glare(out: np.ndarray, glint_px: np.ndarray, effects: ImageEffects) -> None:
    """Add the glare to ``out`` (H, W, 3) float32 in place, over the box outside which it is under 0.1 grey level."""
    H, W = out.shape[:2]
    peak = 255.0 * effects.glare_strength
    reach = effects.glare_core_frac * W + max(effects.glare_falloff_frac * W, 1e-3) * np.sqrt(2.0 * np.log(max(peak / 0.1, 1.0)))
    x0, x1 = max(int(np.floor(glint_px[0] - reach)), 0), min(int(np.ceil(glint_px[0] + reach)) + 1, W)
    y0, y1 = max(int(np.floor(glint_px[1] - reach)), 0), min(int(np.ceil(glint_px[1] + reach)) + 1, H)
    if x1 <= x0 or y1 <= y0:
        return
    light = glare_light((y1 - y0, x1 - x0), np.asarray(glint_px, float) - [x0, y0], effects.glare_strength,
                        effects.glare_core_frac * W / (x1 - x0), effects.glare_falloff_frac * W / (x1 - x0))
    out[y0:y1, x0:x1] += light[..., None]


def apply_effects(image: np.ndarray, effects: ImageEffects, rng: np.random.Generator | None, *,
                  motion_px: np.ndarray | None = None, glint_px: np.ndarray | None = None) -> np.ndarray:
    """The camera's effects on one rendered frame, in the order light meets them: exposure gain, defocus blur,
    motion blur along ``motion_px`` (the ground's motion in the image during the exposure, px), the sun's glare
    about ``glint_px`` and its haze, the appearance shift's exposure gain, shot and read noise, the shift's white
    balance and gamma, then white noise. Noise is drawn from ``rng``. No effect: ``image`` itself."""
    if effects.is_identity:
        return image
    out = image.astype(np.float32)
    if effects.exposure_gain != 1.0:
        out *= effects.exposure_gain
    if effects.blur_sigma_px > 0:
        out = cv2.GaussianBlur(out, (0, 0), effects.blur_sigma_px)
    if motion_px is not None and np.hypot(*motion_px) > 0:
        out = cv2.filter2D(out, -1, line_kernel(motion_px), borderType=cv2.BORDER_REFLECT_101)
    if effects.glare_haze > 0:
        out = out * np.float32(1.0 - effects.glare_haze) + np.float32(255.0 * effects.glare_haze)
    if effects.glare_strength > 0 and glint_px is not None:
        _add_glare(out, glint_px, effects)
    if effects.shift_gain != 1.0:
        out *= np.float32(effects.shift_gain)
    if effects.shot_noise_dn > 0 or effects.read_noise_dn > 0:
        rng = rng if rng is not None else np.random.default_rng(0)
        var = np.float32(effects.shot_noise_dn) * np.clip(out, 0.0, 255.0) + np.float32(effects.read_noise_dn**2)
        out += rng.standard_normal(out.shape, dtype=np.float32) * np.sqrt(var)
    if tuple(effects.shift_gain_bgr) != (1.0, 1.0, 1.0):
        out *= np.asarray(effects.shift_gain_bgr, np.float32)
    if effects.shift_gamma != 1.0:
        out = np.float32(255.0) * cv2.pow(np.clip(out, 0.0, 255.0) / np.float32(255.0), effects.shift_gamma)
    if effects.noise_sigma > 0:
        rng = rng if rng is not None else np.random.default_rng(0)
        out += rng.normal(0.0, effects.noise_sigma, out.shape).astype(np.float32)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)
