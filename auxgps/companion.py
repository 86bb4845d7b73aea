"""The companion process: the link, the camera, the clocks and the 10 Hz timer around the estimator.

Threads: the link's reader hands the autopilot's messages to the estimator; a timer asks it for GPS_INPUT every
1/rate seconds, never waiting on frame processing; the main loop reads the camera and runs each frame through the
estimator, holding the lock only to begin and to finish the frame, not while detecting and locating. Every
estimator call is made under one lock, so that they have one order, the one a recording keeps. Every time is on
this process's monotonic clock.
"""

from __future__ import annotations

import faulthandler
import json
import logging
import os
import threading
import time
from array import array
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from auxgps.config import PipelineConfig
from auxgps.core.estimator import Estimator, EstimatorOptions, FrameResult
from auxgps.errors import LinkError
from auxgps.io.camera import open_camera
from auxgps.io.flight_log import FlightLog
from auxgps.io.link import Decoder, MavLink, Truth
from auxgps.io.map_file import load_maps, save_map, saved_heading
from auxgps.io.recording import Recorder

log = logging.getLogger(__name__)


def lower_this_thread(steps: int) -> int:
    """Raise the calling thread's niceness by ``steps`` (Linux keeps one per thread; threads it starts later,
    OpenCV's among them, inherit it). Returns the new niceness; without per-thread priorities, says so and leaves it."""
    tid = threading.get_native_id()
    try:
        nice = os.getpriority(os.PRIO_PROCESS, tid) + steps
        os.setpriority(os.PRIO_PROCESS, tid, nice)
    except (AttributeError, OSError) as err:  # not Linux, or not allowed
        log.warning("--nice %d: could not lower the frame thread's priority (%s); frames and the timer share one", steps, err)
        return 0
    log.info("frame processing at niceness %d, the GPS_INPUT timer and the link reader above it", nice)
    return nice


class PrimaryTakeover:
    """Opt-in (``--take-primary-on-drift``): while GPS1 is found dragged away from the map and auxgps has a 3D fix,
    make GPS2 the autopilot's primary (GPS_AUTO_SWITCH 0, GPS_PRIMARY 1); put both back as they were when GPS1 is
    trusted again, when auxgps loses its fix, and when it stops. ArduPilot by itself keeps a GPS1 that reports a 3D
    fix as primary, dragged or not. The risks are the README's: a false alarm hands the vehicle to the camera; if
    auxgps dies without restoring them, GPS2 times out after 4 s and the autopilot, told to use it alone, has no
    GPS until they are restored."""

    PARAMS = ("GPS_AUTO_SWITCH", "GPS_PRIMARY")

    def __init__(self, link, event) -> None:
        self.link, self.event = link, event
        self.saved: dict[str, float] = {}
        self.taken = False
        self._asked_t_s = -float("inf")

    def on_param_value(self, msg) -> None:
        name = msg.param_id.rstrip("\x00") if isinstance(msg.param_id, str) else msg.param_id.decode().rstrip("\x00")
        if name in self.PARAMS and not self.taken:
            self.saved[name] = float(msg.param_value)

    def update(self, t_s: float, dragged: bool, have_fix: bool) -> None:
        if len(self.saved) < len(self.PARAMS):
            if t_s - self._asked_t_s > 5.0:  # what to restore, asked for until known
                self._asked_t_s = t_s
                for name in self.PARAMS:
                    self.link.send_param_request(name)
            return
        if dragged and have_fix and not self.taken:
            self.taken = True
            self.link.send_param_set("GPS_AUTO_SWITCH", 0)
            self.link.send_param_set("GPS_PRIMARY", 1)
            self.event(t_s, "GPS1 dragged: GPS2 (auxgps) made primary (GPS_AUTO_SWITCH 0, GPS_PRIMARY 1), as "
                            "--take-primary-on-drift asks")
        elif self.taken and not (dragged and have_fix):
            self.restore(t_s, "GPS1 trusted again" if not dragged else "auxgps has no fix")

    def restore(self, t_s: float, why: str) -> None:
        if not self.taken:
            return
        self.taken = False
        for name in self.PARAMS:
            self.link.send_param_set(name, self.saved[name])
        self.event(t_s, f"{why}: GPS_AUTO_SWITCH {self.saved['GPS_AUTO_SWITCH']:g} and GPS_PRIMARY "
                        f"{self.saved['GPS_PRIMARY']:g} restored")


class StallWatch:
    """Every thread's stack, written to ``path`` when :meth:`tick` has not come for ``timeout_s``: ``faulthandler``'s
    watchdog, whose C thread needs no interpreter lock, so that it reports a stall as it happens, whether a thread
    holds the lock in native code or the process is not scheduled. The GPS_INPUT timer ticks it (1 s stalls of the
    whole process, in two of eight busy SITL flights, are why: docs/faults.md). One per process (faulthandler has one
    watchdog); the file stays empty while nothing stalls."""

    def __init__(self, path: Path, timeout_s: float) -> None:
        self.path, self.timeout_s = Path(path), timeout_s
        self._file = open(self.path, "a")
        self._size = self.path.stat().st_size

    def tick(self) -> None:
        faulthandler.dump_traceback_later(self.timeout_s, repeat=False, file=self._file)

    def wrote(self) -> bool:
        """Whether a stall has been written since the last call (or since the watch began)."""
        size = self.path.stat().st_size
        grew, self._size = size > self._size, size
        return grew

    def close(self) -> None:
        faulthandler.cancel_dump_traceback_later()
        self._file.close()


class FrameStats:
    """What the frame loop kept up with: each frame's processing time, and the time from its capture to the first
    GPS_INPUT sent after it was done (the first that can carry its fix; frames done before GPS_INPUT is sent at all,
    before GPS1's first fix, have none). Thread-safe: the frame loop and the GPS_INPUT timer both report."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._sending = False  # a GPS_INPUT has been sent
        self._done: list[float] = []  # capture times of the frames done since the last GPS_INPUT
        self.processing_ms = array("d")
        self.latency_ms = array("d")

    def frame_done(self, t_capture_s: float, processing_ms: float) -> None:
        with self._lock:
            if self._sending:
                self._done.append(t_capture_s)
            self.processing_ms.append(processing_ms)

    def gps_input_sent(self, t_s: float) -> None:
        with self._lock:
            self.latency_ms.extend((t_s - t) * 1e3 for t in self._done)
            self._done.clear()
            self._sending = True

    def figures(self, delivered: int | None, dropped: int | None) -> dict:
        """Frames processed (and, for a source that counts them, delivered and dropped), with the medians, 99th
        percentiles and maxima of the two times, ms."""
        with self._lock:
            proc, lat = np.asarray(self.processing_ms), np.asarray(self.latency_ms)

        def stats(x):
            return {"median": round(float(np.median(x)), 1), "p99": round(float(np.percentile(x, 99)), 1),
                    "max": round(float(x.max()), 1)} if len(x) else None

        return {"frames_processed": len(proc), "frames_delivered": delivered, "frames_dropped": dropped,
                "processing_ms": stats(proc), "capture_to_gps_input_ms": stats(lat)}


@dataclass(frozen=True)
class RunOptions:
    connect: str
    camera: str
    map_in: list[str] | None = None  # maps to start from: a flight's and prior maps (orthophotos'), merged into one
    map_out: str | None = None
    log_dir: str = "out/run"
    duration_s: float | None = None
    gps_input_rate_hz: float = 10.0
    gps_delay_s: float = 0.1  # GPS_INPUT describes the vehicle this long ago: the autopilot's GPS2_DELAY_MS
    gps1_lag_s: float = 0.1  # a GPS1 reading describes the vehicle this long before its fix time (SITL: SIM_GPS1_LAG_MS)
    record_dir: str | None = None  # record what the estimator sees here (auxgps.io.recording)
    connect_timeout_s: float = 15.0  # at start, how long the autopilot may take to be there
    checkpoint_s: float = 10.0  # with map_out: the map is also written this often while flying, and at every mode change (0: at the end only)
    frame_nice: int = 0  # frame processing this many niceness steps below the timer and the reader (Linux: per thread)
    take_primary_on_drift: bool = False  # opt-in: make GPS2 the autopilot's primary while GPS1 is found dragged
    stall_report_s: float = 0.5  # the GPS_INPUT timer held up this long: every thread's stack to stalls.txt (0: off)
    sim_camera_fps: float | None = None  # sim: cameras only: render this many frames a second in a thread, as a camera delivers


class Companion:
    """auxgps as a process beside the autopilot."""

    def __init__(self, cfg: PipelineConfig, opts: RunOptions) -> None:
        self.cfg, self.opts = cfg, opts
        landmarks = frame = None
        start_map = opts.map_in[0] if opts.map_in else None
        if opts.map_in:
            landmarks, frame = load_maps(opts.map_in)  # MapError: one clear line from the CLI
            if len(opts.map_in) > 1 and opts.record_dir:  # the recording keeps the merged map it started from
                start_map = str(Path(opts.record_dir) / "start_map.npz")
                save_map(start_map, landmarks, frame)
        self.estimator = Estimator(cfg, EstimatorOptions(gps_delay_s=opts.gps_delay_s, gps1_lag_s=opts.gps1_lag_s),
                                   landmarks=landmarks, frame=frame)
        if opts.map_in and self.estimator.heading is not None:
            # The heading error the map's own flight had solved (a checkpoint read after a crash), aged since
            saved = saved_heading(opts.map_in[0])
            if saved is not None:
                self.estimator.heading.restore(saved["offset_rad"], saved["sigma_rad"], max(time.time() - saved["unix_s"], 0.0))
        self.log = FlightLog(opts.log_dir)
        self.recorder = None
        if opts.record_dir:
            self.recorder = Recorder(opts.record_dir, options=asdict(opts), pipeline=asdict(cfg), start_map=start_map)
        self._decoder = Decoder()
        self._reboots_said = 0
        self._lock = threading.Lock()
        self._truth: Truth | None = None
        self._stop = threading.Event()
        # A simulated camera's truth at twice its frame rate: each frame is rendered from a truth under half a frame old
        self.link = MavLink(opts.connect, self._on_message, sim=opts.camera.startswith("sim:"),
                            sim_hz=max(20.0, 2.0 * (opts.sim_camera_fps or 0.0)))
        est = self.estimator
        self.camera = open_camera(opts.camera, est.camera, est.R_body_cam, truth=lambda: self._truth, sim_fps=opts.sim_camera_fps)
        self.frame_stats = FrameStats()
        self.sent = 0
        self._mode = None  # the last GPS_INPUT's mode (timer thread)
        self._checkpoint_wanted = threading.Event()  # a mode change asks the frame thread for a checkpoint
        self._last_checkpoint_s = time.monotonic()
        self.checkpoints = 0
        self._dropped_said = (time.monotonic(), 0)  # (when, the camera's dropped count then)
        self.primary = PrimaryTakeover(self.link, self._event) if opts.take_primary_on_drift else None

    def _event(self, t_s: float, text: str) -> None:
        self.log.event(t_s, text, self._decoder.clock.boot_s(t_s))

    # -- messages from the autopilot (reader thread) --------------------------------------------------------

    def _on_message(self, msg, arrival_s: float) -> None:
        with self._lock:
            if self.recorder is not None:
                self.recorder.message(msg, arrival_s)
            if self.primary is not None and msg.get_type() == "PARAM_VALUE":
                self.primary.on_param_value(msg)
            rec = self._decoder(msg, arrival_s)
            note = None
            if isinstance(rec, Truth):
                self._truth = rec  # only the simulated camera may see it
            elif rec is not None:
                note = self.estimator.feed(rec)
        clock = self._decoder.clock  # this thread's alone: what follows needs no lock, and holds up no GPS_INPUT
        if clock.reboots != self._reboots_said:
            self._reboots_said = clock.reboots
            self.link.request_streams()  # forgotten over a restart, whatever its SRn_ rates give instead
            before_s, after_s = clock.last_reboot_s
            self._event(arrival_s, f"autopilot rebooted: its boot clock went back from {before_s:.1f} s to "
                        f"{after_s:.1f} s; stamps follow the new clock, message rates asked for again")
        if note:
            self._event(rec.t_s, note)

    # -- GPS_INPUT at a steady rate (timer thread) ----------------------------------------------------------

    def _gps_input_loop(self) -> None:
        period = 1.0 / self.opts.gps_input_rate_hz
        next_t = time.monotonic()
        watch = StallWatch(Path(self.opts.log_dir) / "stalls.txt", period + self.opts.stall_report_s) \
            if self.opts.stall_report_s > 0 else None
        try:
            while not self._stop.is_set():
                next_t += period
                if watch is not None:
                    watch.tick()
                self._send_gps_input()
                delay = next_t - time.monotonic()
                if delay < -period:
                    self._event(time.monotonic(), f"GPS_INPUT timer held up {period - delay:.2f} s"
                                + (f" (every thread's stack then: {watch.path})" if watch is not None and watch.wrote() else ""))
                    next_t = time.monotonic()  # fell behind (a stalled machine): restart the schedule, do not burst
                elif delay > 0:
                    self._stop.wait(delay)
        finally:
            if watch is not None:
                watch.close()

    def _send_gps_input(self) -> None:
        t_unix_s = time.time()
        with self._lock:
            t_s = time.monotonic()
            if self.recorder is not None:
                self.recorder.output(t_s, t_unix_s)
            out = self.estimator.output(t_s, t_unix_s)
        if out.decision.mode != self._mode:
            if self._mode is not None:
                self._checkpoint_wanted.set()
            self._mode = out.decision.mode
        if out.gps is None:
            return
        if self.link.send_gps_input(out.gps, int((t_unix_s - self.opts.gps_delay_s) * 1e6)):
            self.sent += 1
            self.frame_stats.gps_input_sent(time.monotonic())
        self.log.output(out)
        if out.decision.status:
            self.link.send_statustext(out.decision.status)
            self._event(out.t_s, out.decision.status)
        if self.primary is not None:
            self.primary.update(out.t_s, self.estimator.supervisor.dragged_at_s is not None, out.gps.fix_type >= 3)

    # -- frames (main thread) -------------------------------------------------------------------------------

    def _process(self, frame) -> FrameResult:
        t0 = time.monotonic()
        with self._lock:
            k = self.recorder.begin(frame) if self.recorder is not None else None
            job = self.estimator.begin_frame(frame)
        if isinstance(job, FrameResult):
            res = job
        else:
            work = self.estimator.process_frame(job)  # slow: detection, mapping, locating; the map is this thread's
            with self._lock:
                if self.recorder is not None:
                    self.recorder.finish(k)
                res = self.estimator.finish_frame(work)
        self.frame_stats.frame_done(frame.t_s, (time.monotonic() - t0) * 1e3)
        self.log.frame(res, self.estimator.frame)
        if res.note:
            self._event(res.t_s, res.note)
            log.warning("%s", res.note)
        return res

    # -- map checkpoints (main thread, which alone changes the map) -----------------------------------------

    def _checkpoint(self, why: str) -> None:
        """Write the map to ``--save-map`` atomically, so that a crash loses at most ``checkpoint_s`` of it."""
        est = self.estimator
        if not self.opts.map_out or est.frame is None:
            return
        t0 = time.monotonic()
        heading = None
        if est.heading is not None:
            h = est.heading.at(time.monotonic())
            heading = {"offset_rad": h.offset_rad, "sigma_rad": h.sigma_rad, "unix_s": time.time()}
        try:
            save_map(self.opts.map_out, est.landmarks, est.frame, heading=heading)
        except OSError as err:  # a full or read-only disk must not end the flight; the previous checkpoint stays
            log.error("map checkpoint to %s failed (%s): %s", self.opts.map_out, why, err)
            return
        finally:
            self._last_checkpoint_s = time.monotonic()
        self.checkpoints += 1
        log.info("map of %d landmarks saved to %s (%s, %.0f ms)", len(est.landmarks), self.opts.map_out, why,
                 (time.monotonic() - t0) * 1e3)

    def _say_dropped_frames(self, every_s: float = 10.0) -> None:
        """Every ``every_s``, how many frames the camera delivered that the frame loop never took (a live source
        keeps only the newest: processing slower than the camera drops the older ones, it never queues them)."""
        t_said, n_said = self._dropped_said
        now = time.monotonic()
        if now - t_said < every_s:
            return
        n = getattr(self.camera, "dropped", None) or 0
        self._dropped_said = (now, n)
        if n > n_said:
            line = f"camera: {n - n_said} frames dropped in {now - t_said:.0f} s, processing slower than the camera (the newest is kept)"
            self._event(now, line)
            log.info("%s", line)

    def _say_frame_figures(self) -> None:
        """The flight's frame figures, to frames.json in the log folder and as an event line."""
        fig = self.frame_stats.figures(getattr(self.camera, "delivered", None), getattr(self.camera, "dropped", None))
        try:
            (Path(self.opts.log_dir) / "frames.json").write_text(json.dumps(fig, indent=2))
        except OSError as err:  # a full disk at the end must not hide the rest of the shutdown
            log.error("frames.json not written: %s", err)
        lat, proc = fig["capture_to_gps_input_ms"], fig["processing_ms"]
        line = f"frames: {fig['frames_processed']} processed"
        if fig["frames_delivered"]:
            line += f" of {fig['frames_delivered']} the camera delivered ({fig['frames_dropped']} dropped, the newest kept)"
        if proc:
            line += f"; processing median {proc['median']:.0f} ms, p99 {proc['p99']:.0f} ms"
        if lat:
            line += f"; capture to GPS_INPUT median {lat['median']:.0f} ms, p99 {lat['p99']:.0f} ms"
        self._event(time.monotonic(), line)
        log.info("%s", line)

    def _checkpoint_if_due(self) -> None:
        if self._checkpoint_wanted.is_set():
            self._checkpoint_wanted.clear()
            self._checkpoint("mode change")
        elif self.opts.checkpoint_s > 0 and time.monotonic() - self._last_checkpoint_s >= self.opts.checkpoint_s:
            self._checkpoint("checkpoint")

    def run(self) -> int:
        self.link.open(self.opts.connect_timeout_s)  # LinkError: one clear line from the CLI
        self.link.start()
        timer = threading.Thread(target=self._gps_input_loop, daemon=True, name="gps-input")
        timer.start()
        if self.opts.frame_nice:
            lower_this_thread(self.opts.frame_nice)  # after the reader and the timer started: they keep theirs
        t_end = None if self.opts.duration_s is None else time.monotonic() + self.opts.duration_s
        try:
            while not self._stop.is_set() and (t_end is None or time.monotonic() < t_end):
                if self.link.failure is not None:
                    raise LinkError(f"the link's reader stopped: {type(self.link.failure).__name__}: {self.link.failure}")
                self._checkpoint_if_due()
                self._say_dropped_frames()
                frame = self.camera.read()
                if frame is None:
                    time.sleep(0.005)
                    continue
                self._process(frame)
        except KeyboardInterrupt:
            log.info("interrupted")
        finally:
            self._stop.set()
            timer.join(timeout=2.0)
            if self.primary is not None:
                self.primary.restore(time.monotonic(), "auxgps stopping")
                time.sleep(0.2)  # let the PARAM_SETs leave before the link closes
            self.link.stop()
            self.camera.close()
            self._checkpoint("end of flight")
            self._say_frame_figures()
            self.log.close()
            if self.recorder is not None:
                stats = self.recorder.close()
                log.info("recording in %s: %s", self.opts.record_dir, stats)
        return 0
