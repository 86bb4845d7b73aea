"""The real-time benchmark: per-frame time of the pipeline on one thread, at map sizes up to a million landmarks.

A simulated mapping survey and a different positioning flight are flown over a feature-rich world (a procedural
gravel ground and the thesis' four 0.5 m cubes); every frame is rendered before it is timed, so rendering is
never counted. Each frame then goes through :class:`auxgps.core.estimator.Estimator`, the code ``auxgps run``
flies, with a :class:`StageClock` passed in as its stopwatch; the stages are exclusive times:

- checking: the frame's grey conversion and :class:`auxgps.core.frame_check.FrameCheck` (frozen, covered,
  blinded, blurred);
- tracking: a followed frame's optical flow (:mod:`auxgps.core.tracking`: the last fix's inliers carried into it,
  in place of detection and matching);
- detection: :meth:`FeatureDetector.detect` (ORB, Harris filter, sub-pixel refinement);
- matching: finding candidate landmarks (the spatial index) and pairing features with them;
- solving: the rest of :meth:`Localiser.locate` (consensus, refinement, rival check) and, for a mapping frame,
  the rest of :meth:`Mapper.process` (projection, fusing observations, adding landmarks) and the self-check
  locating that a mapping frame also gets;
- filtering: the fix into the filter (roll back, update, take the later steps again).

The positioning flight is replayed against the map the survey built, and against that map padded with
synthetic landmarks (random descriptors, usable, at the real map's density) to each size in ``map_sizes``,
over a proportionally larger square with the real map in its middle: the frames' own landmarks are in it, and
the index must find them among the rest. A method to compare (the thesis' baseline, :mod:`auxgps.evaluation.thesis_baseline`) is run on the
same frames through the small :class:`Method` interface.

Latency from capture to the GPS_INPUT carrying a frame is modelled on :mod:`auxgps.companion`: the frame is
processed (detection, matching, solving: the times measured here), its fix goes into the filter (measured), and
the next tick of the 10 Hz GPS_INPUT timer, which runs on its own clock, sends the estimate with it. So
latency = measured processing + a wait uniform over one output period (seeded), for every fix the filter
accepted. The camera's own exposure-to-memory delay and the serial link are not included.
"""

from __future__ import annotations

import os
import platform
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from typing import Callable, Protocol

import cv2
import numpy as np

from auxgps.config import PipelineConfig, parse_as
from auxgps.core.camera import CameraPose, camera_from_config
from auxgps.core.estimator import Estimator, EstimatorOptions, FrameResult
from auxgps.core.events import Frame
from auxgps.core.features import detect, greedy_one_to_one
from auxgps.core.geometry import R_body_cam_from_mount
from auxgps.core.landmarks import LandmarkMap
from auxgps.core.localise import Fix
from auxgps.sim.flight import SimConfig, Telemetry, fly, imu_bias, lawnmower_waypoints, sense
from auxgps.sim.sensors import Sensors
from auxgps.sim.render import Renderer
from auxgps.sim.texture import gravel_texture
from auxgps.sim.world import Cube, World, _color_to_bgr, load_world

STAGES = ("checking", "tracking", "detection", "matching", "solving", "filtering")

#: The thesis' four 0.5 m cubes (config/worlds/cubes4_0.5m_different.yaml): (north, east, colour, yaw).
_CUBES = ((2.0, 1.0, "red", 0.0), (-5.0, -4.0, "blue", 20.0), (-6.0, 6.0, "green", 35.0), (5.0, -6.0, "white", 50.0))


@dataclass(frozen=True)
class BenchConfig:
    """What the benchmark flies and measures.

    ``alt_m`` survey height, m; ``fps`` frames per second of the positioning flight, ``mapping_fps`` of the
    mapping survey (1 keeps the survey's map under 10 thousand landmarks, the smallest padded size, while every
    ground point is still seen in some 17 frames per leg); ``map_sizes`` landmark counts the
    map is padded to; ``reported_map`` the size whose figures are the headline ``positioning`` ones;
    ``texture_m_per_px`` ground texture scale, m/px; ``output_rate_hz`` the GPS_INPUT rate; ``world`` a world
    file (an orthophoto world, say) flown instead of the gravel and cubes, its surveys those of the sim config.
    """

    alt_m: float = 15.0
    fps: float = 2.0
    mapping_fps: float = 1.0
    seed: int = 1
    map_sizes: tuple[int, ...] = (10_000, 100_000, 1_000_000)
    reported_map: int = 100_000
    texture_m_per_px: float = 0.02
    output_rate_hz: float = 10.0
    world: str | None = None  # a world file or name (auxgps.sim.world.load_world) instead of the gravel and cubes


class Method(Protocol):
    """A positioning method run on the benchmark's frames beside the pipeline (the thesis' baseline)."""

    name: str

    def map_frame(self, image_bgr: np.ndarray, tel: Telemetry) -> dict[str, float]:
        """Learn from one mapping frame with GPS; return its stage times, ms."""

    def locate_frame(self, image_bgr: np.ndarray, tel: Telemetry) -> tuple[np.ndarray | None, dict[str, float]]:
        """Position one frame without GPS: north/east (2,) m or None, and its stage times, ms."""

    def start_positioning(self) -> None:
        """The positioning flight begins (a method working on frame pairs forgets the last mapping frame)."""


def tiny_sim_config(sim: SimConfig) -> SimConfig:
    """``sim`` with surveys of 4 m by 4 m and GPS lost after 2 s: a benchmark of seconds, for smoke tests."""
    small = dict(north_min_m=-2.0, north_max_m=2.0, east_min_m=-2.0, east_max_m=2.0, spacing_m=2.0)
    return parse_as(
        SimConfig,
        dict(asdict(sim), mapping=dict(asdict(sim.mapping), **small), positioning=dict(asdict(sim.positioning), **small),
             denial=dict(asdict(sim.denial), gps_until_s=2.0)),
        "tiny benchmark",
    )


def machine_info() -> dict:
    """Where the figures were taken: CPU, load averages (1, 5, 15 min), thread settings, library versions."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            names = [line.split(":", 1)[1].strip() for line in f if line.startswith("model name")]
        cpu = names[0] if names else cpu
    except OSError:
        pass
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "load_average": [round(x, 2) for x in os.getloadavg()] if hasattr(os, "getloadavg") else None,
        "opencv_threads": cv2.getNumThreads(),
        "thread_env": {k: os.environ.get(k) for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")},
        "python": platform.python_version(),
        "numpy": np.__version__,
        "opencv": cv2.__version__,
        "cpu_steal_s": cpu_steal_s(),
    }


def cpu_steal_s() -> float | None:
    """CPU time the hypervisor has taken from this virtual machine since it booted (the steal column of the ``cpu``
    line of /proc/stat), s; None where there is none to read. What it grows by over a run is time the host took."""
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
        return int(fields[8]) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


def reference_ms(repeats: int = 11) -> dict[str, float]:
    """Thread CPU time of two fixed pieces of work, the median of ``repeats``, ms, so that figures taken on two
    machines can be set side by side:

    - ``opencv``: the default detector's ORB (600 features, two levels, described at one angle) on a seeded
      1280x720 gravel frame, as a mapping frame is detected;
    - ``python``: a greedy one-to-one over 3000 seeded pairs, taken pair by pair as the mapper does, and a sort of
      20 000 seeded floats: the interpreter's and NumPy's share of a frame.
    """
    pipeline = PipelineConfig()
    orb = Estimator(pipeline).detector.orb  # the flying detector's ORB at its lowest FAST threshold
    grey = cv2.cvtColor(gravel_texture(1280, seed=1)[:720], cv2.COLOR_BGR2GRAY)
    rng = np.random.default_rng(1)
    a, b, x = rng.integers(0, 600, 3000), rng.integers(0, 1500, 3000), rng.random(20_000)

    def median_ms(work) -> float:
        times = []
        for _ in range(repeats):
            t0 = time.thread_time()
            work()
            times.append(time.thread_time() - t0)
        return round(float(np.median(times)) * 1e3, 3)

    return {"opencv": median_ms(lambda: detect([orb], grey, pipeline.detector.min_harris, 0.0)),
            "python": median_ms(lambda: (greedy_one_to_one(a, b), np.sort(x)))}


def bench_report(fig: dict) -> str:
    """The benchmark's figures as a few lines of text."""
    pos, mp = fig["positioning"], fig["mapping"]

    def ms(x):
        return "-" if x is None else f"{x:.1f}"

    def m(x):
        return "-" if x is None else f"{x:.3f}"

    bc = fig["config"]["bench"]
    lines = [
        f"world: {bc.get('world') or 'gravel and four 0.5 m cubes'}, at {bc['alt_m']:g} m, frames at 1280x720 on one thread",
        f"machine: {fig['machine']['cpu']}, load average at start {fig['machine']['load_average']}, at end {fig['machine_end']['load_average']}"
        + _host_note(fig),
        f"positioning frames ({pos['frames']}, map of {pos['map_landmarks']} landmarks, {pos['features_per_frame']:.0f} features/frame): "
        f"median {ms(pos['median_ms'])} ms, p99 {ms(pos['p99_ms'])} ms, min {ms(pos['min_ms'])}, max {ms(pos['max_ms'])} "
        f"(CPU median {ms(pos['cpu_ms']['median'])} ms)",
        "  stages, median ms: " + ", ".join(f"{k} {ms(v['median'])}" for k, v in pos["per_frame_ms"].items() if k != "total"),
        f"  mean {ms(pos['mean_ms'])} ms; followed by optical flow {pos['followed']['frames']} frames ({pos['followed']['share']:.0%}), "
        f"median {ms(pos['followed']['median_ms'])} ms; full frames median {ms(pos['followed']['full_median_ms'])} ms",
        f"  fixes: RMS {m(pos['fixes']['rms_m'])} m, p95 {m(pos['fixes']['p95_m'])} m, max {m(pos['fixes']['max_m'])} m, availability {pos['fixes']['availability']:.2f}",
        f"  capture to GPS_INPUT: median {ms(pos['latency_ms']['median'])} ms, p99 {ms(pos['latency_ms']['p99'])} ms, max {ms(pos['latency_ms']['max'])} ms",
        f"mapping frames ({mp['frames']}, {mp['features_per_frame']:.0f} features/frame, {mp['landmarks']} landmarks made): "
        f"median {ms(mp['median_ms'])} ms, p99 {ms(mp['p99_ms'])} ms; stages, median ms: "
        + ", ".join(f"{k} {ms(v['median'])}" for k, v in mp["per_frame_ms"].items() if k != "total"),
        "map scale, median (p99) ms per positioning frame: "
        + ", ".join(f"{k}: {ms(v)} ({ms(fig['scaling_p99'][k])})" for k, v in fig["scaling"].items())
        + (f"; growth {100 * fig['scaling_growth']:.0f} % (CPU time: {100 * fig['scaling_growth_cpu']:.0f} %)" if fig.get("scaling_growth") is not None else ""),
        f"memory: {fig['bytes_per_landmark']:.1f} bytes per landmark (columns, slack and index of the {pos['map_landmarks']}-landmark map)",
    ]
    if "baseline" in fig:
        b, o, r = fig["baseline"], fig["ours"], fig["ratios"]["baseline"]
        lines.append(
            f"thesis baseline on the same frames: median {ms(b['median_ms'])} ms, RMS {m(b['rms_m'])} m ({b['fixes']['count']} fixes of "
            f"{pos['frames']} frames); ours (real map): median {ms(o['median_ms'])} ms, RMS {m(o['rms_m'])} m; "
            f"baseline / ours: time {r['time_baseline_over_ours'] or 0:.2f}, RMS {r['rms_baseline_over_ours'] or 0:.2f}"
        )
    return "\n".join(lines)


def _host_note(fig: dict) -> str:
    """The machine's reference work and the CPU the host took during the run, for the report's machine line."""
    start, end = fig["machine"], fig.get("machine_end", {})
    ref = start.get("reference_ms")
    note = f"; reference work: OpenCV {ref['opencv']:.1f} ms, Python {ref['python']:.1f} ms" if ref else ""
    if start.get("cpu_steal_s") is not None and end.get("cpu_steal_s") is not None:
        note += f"; the host took {end['cpu_steal_s'] - start['cpu_steal_s']:.1f} s of CPU during the run"
    return note


def bench_world(sim: SimConfig, cfg: BenchConfig) -> World:
    """The survey area and its surroundings under a seeded gravel texture, with the thesis' four 0.5 m cubes."""
    # The texture covers every survey and the camera's reach around it (its borders are mirrored beyond).
    extent_m = 2.0 * (max(abs(v) for s in (sim.mapping, sim.positioning) for v in (s.north_min_m, s.north_max_m, s.east_min_m, s.east_max_m)) + 1.5 * cfg.alt_m)
    texture = gravel_texture(int(np.ceil(extent_m / cfg.texture_m_per_px)), cfg.seed)
    cubes = tuple(Cube(np.array([n, e]), 0.5, float(np.deg2rad(yaw)), _color_to_bgr(c)) for n, e, c, yaw in _CUBES)
    from auxgps.core.geometry import LocalFrame

    return World(LocalFrame(47.397742, 8.545594, 488.0), cubes, None, texture, cfg.texture_m_per_px, "bench", "gravel and four 0.5 m cubes")


# -- timing helpers ------------------------------------------------------------------------------------------


class StageClock:
    """The benchmark's stopwatch for the estimator's stages: each stage's exclusive time, ms (a stage inside
    another, such as matching inside locating, is not counted in the outer one), until read and reset."""

    def __init__(self) -> None:
        self.ms: dict[str, float] = {}
        self._stack: list[list] = []  # [stage, time it last (re)started]

    @contextmanager
    def __call__(self, stage: str):
        now = time.perf_counter()
        if self._stack:
            outer = self._stack[-1]
            self.ms[outer[0]] = self.ms.get(outer[0], 0.0) + (now - outer[1]) * 1e3
        self._stack.append([stage, now])
        try:
            yield
        finally:
            now = time.perf_counter()
            name, t0 = self._stack.pop()
            self.ms[name] = self.ms.get(name, 0.0) + (now - t0) * 1e3
            if self._stack:
                self._stack[-1][1] = now

    def take(self) -> dict[str, float]:
        """The stage times since the last take, as the benchmark's stages (checking, detection, matching, solving,
        filtering), ms."""
        ms, self.ms = self.ms, {}
        row = {"checking": ms.get("checking", 0.0), "detection": ms.get("detection", 0.0), "matching": ms.get("matching", 0.0),
               "solving": ms.get("locating", 0.0) + ms.get("mapping", 0.0)}
        if "tracking" in ms:
            row["tracking"] = ms["tracking"]
        if "filtering" in ms:
            row["filtering"] = ms["filtering"]
        return row


def _stats_ms(x) -> dict:
    x = np.asarray(x, float)
    if len(x) == 0:
        return {"min": None, "median": None, "p99": None, "max": None}
    return {"min": float(x.min()), "median": float(np.median(x)), "p99": float(np.percentile(x, 99)), "max": float(x.max())}


def _stage_table(rows: list[dict]) -> dict:
    """Per-stage and total statistics of per-frame stage times (ms)."""
    out = {"total": _stats_ms([sum(r.values()) for r in rows])}
    for s in STAGES:
        if any(s in r for r in rows):
            out[s] = _stats_ms([r.get(s, 0.0) for r in rows])
    return out


# -- the flights -----------------------------------------------------------------------------------------------


def _render(renderer: Renderer, traj, i: int, R_body_cam: np.ndarray, effects, rng) -> np.ndarray:
    pose = CameraPose(traj.p_ned_m[i].copy(), traj.R_ned_body(i) @ R_body_cam)
    return renderer.render(pose, effects, rng, v_ned_m_s=traj.v_ned_m_s[i]).image_bgr


def _map_flight(world, pipeline, sim, cfg, methods, rng_seq, progress):
    """Fly the mapping survey through the estimator (GPS1 throughout), timing each frame's stages; let each
    method learn from the same frames. Returns the map, stage rows, features per frame, the methods' rows."""
    rng_fly, rng_tel, rng_img, rng_imu, rng_method = (np.random.default_rng(s) for s in rng_seq.spawn(5))
    clock = StageClock()
    est = Estimator(pipeline, frame=world.frame, stopwatch=clock)
    renderer = Renderer(world, est.camera)
    effects = sim.image_effects()
    traj = fly(lawnmower_waypoints(sim.mapping, cfg.alt_m), sim.mapping.speed_m_s, sim.vehicle, rng_fly, sim.dt_s)
    sensors = Sensors(traj, world.frame, sim.noise, rng_tel=rng_tel, rng_imu=rng_imu, bias_body_m_s2=imu_bias(sim.noise, rng_imu),
                      gps1_lag_s=est.options.gps1_lag_s)
    frame_every = max(1, int(round(1.0 / (cfg.mapping_fps * sim.dt_s))))
    rows, n_feat, method_rows = [], [], {m.name: [] for m in methods}
    for i in range(len(traj.t_s)):
        for event in sensors.events_at(i):
            est.feed(event)
        if i % frame_every:
            continue
        image = _render(renderer, traj, i, est.R_body_cam, effects, rng_img)
        clock.take()
        res = est.on_frame(Frame(float(traj.t_s[i]), image))
        row = clock.take()
        if res.mapped is not None:
            rows.append(row)
            n_feat.append(len(res.features))
        tel = sense(traj, i, sim.noise, rng_method)  # the methods compared get the autopilot's telemetry as it was
        for m in methods:
            method_rows[m.name].append(m.map_frame(image, tel))
        if progress:
            progress()
    return est.landmarks, rows, n_feat, method_rows


@dataclass
class _PositioningScript:
    """The positioning flight, sensed once: per simulation step the autopilot's events, and the frames (images
    rendered in advance) with the telemetry the methods compared get and the truth. Replayed identically for every
    map."""

    t_s: np.ndarray
    events: dict = field(default_factory=dict)  # step -> [telemetry events]
    frames: dict = field(default_factory=dict)  # step -> (image, Telemetry, truth ne (2,))


def _positioning_script(world, pipeline, sim, cfg, rng_seq, progress) -> _PositioningScript:
    """Fly and sense the positioning flight once; render its frames from shortly after GPS1's loss (untimed).

    Frames start ``POSITIONING_FROM_S`` after the loss, once GPS1's first no-fix report has reached the estimator
    (its lag): every frame timed is a positioning frame, and none feeds the padded maps."""
    rng_fly, rng_tel, rng_img, rng_imu, rng_method = (np.random.default_rng(s) for s in rng_seq.spawn(5))
    camera = camera_from_config(pipeline.camera)
    m = pipeline.mount
    R_body_cam = R_body_cam_from_mount(*np.deg2rad([m.roll_deg, m.pitch_deg, m.yaw_deg]))
    renderer = Renderer(world, camera)
    effects = sim.image_effects(after_gps_loss=True)
    traj = fly(lawnmower_waypoints(sim.positioning, cfg.alt_m), sim.positioning.speed_m_s, sim.vehicle, rng_fly, sim.dt_s)
    den = sim.denial
    sensors = Sensors(traj, world.frame, sim.noise, rng_tel=rng_tel, rng_imu=rng_imu, bias_body_m_s2=imu_bias(sim.noise, rng_imu),
                      gps1_lag_s=EstimatorOptions().gps1_lag_s, gps_denied_from_s=den.gps_until_s)
    frame_every = max(1, int(round(1.0 / (cfg.fps * sim.dt_s))))
    script = _PositioningScript(traj.t_s)
    for i in range(len(traj.t_s)):
        script.events[i] = sensors.events_at(i)
        if traj.t_s[i] >= den.gps_until_s + POSITIONING_FROM_S and i % frame_every == 0:
            tel = sense(traj, i, sim.noise, rng_method, gps_ok=False)
            script.frames[i] = (_render(renderer, traj, i, R_body_cam, effects, rng_img), tel, traj.p_ned_m[i, :2].copy())
            if progress:
                progress()
    return script


#: Frames of the positioning flight are timed from this long after GPS1's loss, s (see _positioning_script).
POSITIONING_FROM_S = 0.3


@dataclass
class _Replay:
    rows: list  # per frame: stage ms
    n_features: list
    fix_err_m: list  # per fix
    latency_ms: list  # per accepted fix
    n_frames: int
    n_fixes: int
    cpu_ms: list = field(default_factory=list)  # per frame, this thread's CPU time for beginning and processing it
    followed: list = field(default_factory=list)  # per frame: its fix came from following the last one's inliers


class _Run:
    """One map's replay of the positioning flight: its estimator and stage clock, fixes waiting to be finished."""

    def __init__(self, landmarks: LandmarkMap, world, pipeline, seed: int) -> None:
        self.map = landmarks
        self.clock = StageClock()
        self.est = Estimator(pipeline, landmarks=landmarks, frame=world.frame, stopwatch=self.clock)
        # The GPS_INPUT timer runs on its own clock (a thread of the companion), not locked to the camera's: the
        # wait for its next tick after a fix is ready is uniform over one period, drawn here per fix (seeded).
        self.rng_tick = np.random.default_rng(seed + 7)
        self.pending: list[tuple[float, object, int]] = []  # (finish time, work, its row)
        self.rec = _Replay([], [], [], [], 0, 0)


def _replay_positioning(script: _PositioningScript, world, maps: list[LandmarkMap], pipeline, sim, cfg, seed, progress) -> list[_Replay]:
    """Run the positioning flight against each of ``maps``, each through its own estimator.

    The maps are replayed in lockstep, each frame on every map in turn (starting with a different map at each
    frame), so that a change in the machine's load while the benchmark runs falls on all of them alike. A frame is
    begun and processed at its capture and finished (its fix fused) ``fix_latency_s`` later, as in ``eval``.
    """
    period_s = 1.0 / cfg.output_rate_hz
    runs = [_Run(m, world, pipeline, seed) for m in maps]
    n_frame = 0
    for i, t in enumerate(script.t_s):
        t = float(t)
        for run in runs:
            for event in script.events[i]:
                run.est.feed(event)
            while run.pending and run.pending[0][0] <= t + 1e-9:
                _, work, k = run.pending.pop(0)
                run.clock.take()
                res = run.est.finish_frame(work)
                row = run.rec.rows[k]
                row["filtering"] = run.clock.take().get("filtering", 0.0)
                if res.decision is not None and res.decision.accepted:
                    run.rec.latency_ms.append(sum(row.values()) + run.rng_tick.uniform(0.0, period_s) * 1e3)
        if i not in script.frames:
            continue
        image, tel, truth_ne = script.frames[i]
        for j in range(len(runs)):
            run = runs[(j + n_frame) % len(runs)]
            rec = run.rec
            run.clock.take()
            c0 = time.thread_time()
            job = run.est.begin_frame(Frame(t, image))
            if isinstance(job, FrameResult):
                continue
            work = run.est.process_frame(job)
            rec.cpu_ms.append((time.thread_time() - c0) * 1e3)
            rec.rows.append({**run.clock.take(), "filtering": 0.0})
            rec.n_features.append(len(work.features))
            rec.followed.append(isinstance(work.located, Fix) and work.located.followed)
            rec.n_frames += 1
            if isinstance(work.located, Fix):
                rec.n_fixes += 1
                rec.fix_err_m.append(float(np.linalg.norm(work.located.p_ned_m[:2] - truth_ne)))
            run.pending.append((t + sim.denial.fix_latency_s, work, len(rec.rows) - 1))
        n_frame += 1
        if progress:
            progress()
    return [run.rec for run in runs]


# -- the padded maps -------------------------------------------------------------------------------------------


def padded_map(real: LandmarkMap, n_total: int, pipeline: PipelineConfig, rng: np.random.Generator) -> LandmarkMap:
    """``real`` plus synthetic landmarks up to ``n_total``, at the real map's density, around it.

    The real landmarks keep their ids (0 .. n_real-1). The synthetic ones have random descriptors, lie on the
    ground uniformly over a square of ``n_total / n_real`` times the real map's area centred on it, outside the
    real map's box (so that the frames see the ground they saw), and count as usable for positioning.
    """
    n_real = len(real)
    if n_total < n_real:
        raise ValueError(f"cannot pad a map of {n_real} landmarks to {n_total}")
    p = real.p_ned_m[:n_real].astype(float)
    lo, hi = np.percentile(p[:, :2], 0.5, axis=0), np.percentile(p[:, :2], 99.5, axis=0)
    centre, side_real = (lo + hi) / 2.0, max(float(np.sqrt(np.prod(hi - lo))), 1.0)
    side = side_real * np.sqrt(n_total / n_real)
    out = LandmarkMap.from_columns(real.columns(), capacity=n_total)
    n_pad = n_total - n_real
    if n_pad:
        pts = np.zeros((0, 2))
        while len(pts) < n_pad:
            cand = centre + rng.uniform(-side / 2, side / 2, (int(1.3 * (n_pad - len(pts))) + 64, 2))
            outside = np.any((cand < lo) | (cand > hi), axis=1)
            pts = np.vstack([pts, cand[outside]])
        pts = pts[:n_pad]
        desc = rng.integers(0, 256, (n_pad, 32), dtype=np.uint8)
        info = np.repeat(np.diag([1.0 / 0.03**2, 1.0 / 0.03**2, 1.0 / 0.1**2])[None], n_pad, 0)
        ranges = rng.choice(real.descriptor_range_m[:n_real], n_pad) if n_real else np.nan
        ids = out.add(desc, np.column_stack([pts, np.zeros(n_pad)]), info, np.ones(n_pad), ranges)
        m = pipeline.mapping
        out.n_seen[ids] = 2 * m.min_seen
        out.n_visible[ids] = 2 * m.min_seen
        out.chi2_mean[ids] = 1.0
    out.reindex()
    out.sync_index()  # as a map loaded from a file: its index is built before the first frame
    return out


# -- the run ---------------------------------------------------------------------------------------------------


def _fix_stats(err_m: list, n_frames: int) -> dict:
    e = np.asarray(err_m, float)
    if len(e) == 0:
        return {"count": 0, "rms_m": None, "p95_m": None, "max_m": None, "availability": 0.0}
    return {
        "count": int(len(e)),
        "rms_m": float(np.sqrt(np.mean(e**2))),
        "p95_m": float(np.percentile(e, 95)),
        "max_m": float(e.max()),
        "availability": float(len(e) / max(n_frames, 1)),
    }


def _split_ms(rows: list[dict], followed: list[bool]) -> dict:
    """How many frames followed (optical flow) and the median total ms of those and of the full ones."""
    total = np.array([sum(r.values()) for r in rows])
    f = np.array(followed, bool)[: len(total)]
    med = lambda x: float(np.median(x)) if len(x) else None  # noqa: E731
    return {"frames": int(f.sum()), "share": float(f.mean()) if len(f) else 0.0, "median_ms": med(total[f]), "full_median_ms": med(total[~f])}


def _replay_summary(rec: _Replay, landmarks: LandmarkMap) -> dict:
    stages = _stage_table(rec.rows)
    mem = landmarks.memory_bytes()
    return {
        "median_ms": stages["total"]["median"],
        "p99_ms": stages["total"]["p99"],
        "min_ms": stages["total"]["min"],
        "max_ms": stages["total"]["max"],
        "features_per_frame": float(np.median(rec.n_features)) if rec.n_features else 0.0,
        "mean_ms": float(np.mean([sum(r.values()) for r in rec.rows])) if rec.rows else None,
        "per_frame_ms": stages,
        # Frames that followed the last fix's inliers by optical flow, and those that were full ones (detected, matched)
        "followed": _split_ms(rec.rows, rec.followed),
        "fixes": _fix_stats(rec.fix_err_m, rec.n_frames),
        "frames": rec.n_frames,
        "map_landmarks": len(landmarks),
        "memory_bytes": mem,
        "bytes_per_landmark": mem["total"] / max(len(landmarks), 1),
        "latency_ms": _stats_ms(rec.latency_ms),
        "cpu_ms": _stats_ms(rec.cpu_ms),
    }


def run_bench(pipeline: PipelineConfig, sim: SimConfig, cfg: BenchConfig, methods: tuple = (), progress: Callable | None = None) -> dict:
    """Fly, render and time everything; return the benchmark's figures (see the README's table of its JSON)."""
    cv2.setNumThreads(1)
    machine = dict(machine_info(), reference_ms=reference_ms())
    say = progress or (lambda *a, **k: None)
    seq = np.random.SeedSequence(cfg.seed)
    seq_map, seq_pos, seq_pad = seq.spawn(3)
    world = load_world(cfg.world) if cfg.world else bench_world(sim, cfg)

    say(f"mapping flight over {world.source or world.description} at {cfg.alt_m:g} m")
    real, map_rows, map_feat, method_map_rows = _map_flight(world, pipeline, sim, cfg, methods, seq_map, progress and (lambda: say(None)))
    say("positioning flight (rendering)")
    script = _positioning_script(world, pipeline, sim, cfg, seq_pos, progress and (lambda: say(None)))

    results: dict[str, dict] = {}
    rng_pad = np.random.default_rng(seq_pad)
    maps: dict[str, LandmarkMap] = {"real": real}
    for n in sorted(cfg.map_sizes):
        if n < len(real):
            results[str(n)] = {"skipped": f"the real map already holds {len(real)} landmarks"}
            continue
        say(f"padding the map to {n} landmarks")
        maps[str(n)] = padded_map(real, n, pipeline, rng_pad)
    say(f"positioning frames on the real map ({len(real)} landmarks) and the padded ones, in lockstep")
    recs = _replay_positioning(script, world, list(maps.values()), pipeline, sim, cfg, cfg.seed, progress and (lambda: say(None)))
    for (name, lm), rec in zip(maps.items(), recs):
        results[name] = _replay_summary(rec, lm)
    results = {k: results[k] for k in ["real", *[str(n) for n in sorted(cfg.map_sizes)]]}
    del maps, recs

    frames = [script.frames[i] for i in sorted(script.frames)]
    compared = {}
    for m in methods:
        say(f"{m.name} on the same positioning frames")
        m.start_positioning()
        rows, err = [], []
        for image, tel, truth_ne in frames:
            p_ne, stage_ms = m.locate_frame(image, tel)
            rows.append(stage_ms)
            if p_ne is not None:
                err.append(float(np.linalg.norm(np.asarray(p_ne)[:2] - truth_ne)))
            if progress:
                say(None)
        st = _stage_table(rows)
        fx = _fix_stats(err, len(frames))
        compared[m.name] = {
            "median_ms": st["total"]["median"],
            "p99_ms": st["total"]["p99"],
            "rms_m": fx["rms_m"],
            "p95_m": fx["p95_m"],
            "fixes": fx,
            "per_frame_ms": st,
            "mapping_per_frame_ms": _stage_table(method_map_rows[m.name]),
        }

    reported = results.get(str(cfg.reported_map), {})
    if "skipped" in reported or not reported:
        reported = results["real"]
    real_res = results["real"]
    out = {
        "positioning": {**reported, "map": str(cfg.reported_map) if str(cfg.reported_map) in results else "real"},
        "mapping": {
            "median_ms": _stage_table(map_rows)["total"]["median"],
            "p99_ms": _stage_table(map_rows)["total"]["p99"],
            "per_frame_ms": _stage_table(map_rows),
            "features_per_frame": float(np.median(map_feat)) if map_feat else 0.0,
            "frames": len(map_rows),
            "landmarks": len(real),
            "memory_bytes": real.memory_bytes(),
        },
        "scaling": {k: v.get("median_ms") for k, v in results.items() if k != "real"},
        "scaling_p99": {k: v.get("p99_ms") for k, v in results.items() if k != "real"},
        "scaling_cpu": {k: v["cpu_ms"]["median"] if "cpu_ms" in v else None for k, v in results.items() if k != "real"},
        "maps": results,
        "bytes_per_landmark": reported["bytes_per_landmark"],
        "latency_ms": reported["latency_ms"],
        "ours": {"median_ms": real_res["median_ms"], "p99_ms": real_res["p99_ms"], "rms_m": real_res["fixes"]["rms_m"], "p95_m": real_res["fixes"]["p95_m"], "map": "real"},
        "config": {"bench": asdict(cfg), "pipeline": asdict(pipeline), "sim": asdict(sim)},
        "machine": machine,
        "machine_end": machine_info(),
    }
    sizes = [k for k in out["scaling"] if out["scaling"][k] is not None]
    if len(sizes) >= 2:
        out["scaling_growth"] = out["scaling"][sizes[-1]] / out["scaling"][sizes[0]] - 1.0
        out["scaling_growth_cpu"] = out["scaling_cpu"][sizes[-1]] / out["scaling_cpu"][sizes[0]] - 1.0
    for name, c in compared.items():
        out[name] = c
        ratio = lambda a, b: (a / b) if (a is not None and b) else None  # noqa: E731
        out.setdefault("ratios", {})[name] = {
            "time_baseline_over_ours": ratio(c["median_ms"], out["ours"]["median_ms"]),
            "rms_baseline_over_ours": ratio(c["rms_m"], out["ours"]["rms_m"]),
        }
    return out
