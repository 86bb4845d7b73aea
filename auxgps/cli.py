"""The `auxgps` command. Each subcommand parses its arguments, then calls one function.

Any :class:`AuxGpsError` becomes one line on stderr and exit code 1.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
from pathlib import Path

import numpy as np
from tabulate import tabulate

from auxgps.config import load_pipeline_config
from auxgps.errors import AuxGpsError, ConfigError

DEMO_WORLD = "cubes4_0.5m_different"


def _fmt(x, unit="", digits=3) -> str:
    if x is None:
        return "-"
    if isinstance(x, float):
        return f"{x:.{digits}f}{unit}"
    return f"{x}{unit}"


def _heights(h: dict) -> str:
    lo, hi = h["min_m"], h["max_m"]
    return f"{lo:.0f} m" if hi - lo < 1.0 else f"{lo:.0f} to {hi:.0f} m (median {h['median_m']:.0f})"


def summary_table(summary: dict) -> str:
    """The on-screen table of one scenario's pooled figures."""
    lm, fx, ma, ms = summary["landmarks"], summary["fixes"], summary["mission_average"], summary["per_frame_ms"]
    rows = [
        ["landmark horizontal error (seen > 10 times)", lm["count"], _fmt(lm["rms_m"]), _fmt(lm["median_m"]), "-", _fmt(lm["max_m"])],
        ["per-frame fix horizontal error", fx["count"], _fmt(fx["rms_m"]), _fmt(fx["median_m"]), _fmt(fx["p95_m"]), _fmt(fx["max_m"])],
    ]
    fu = summary["fused"]
    rows.append(["fused output (10 Hz) while GPS-denied", fu["count"], _fmt(fu["rms_m"]), "-", _fmt(fu["p95_m"]), _fmt(fu["max_m"])])
    table = tabulate(rows, headers=["metric (m)", "count", "RMS", "median", "p95", "max"], tablefmt="simple")
    sc = summary["scenario"]
    lines = [
        f"{Path(sc['world']).name} at {_fmt(sc['altitude_m'], ' m', 0) if sc['altitude_m'] else 'the mission heights'},"
        f" {sc['runs']} run(s) at {sc['fps']:g} frames/s"
        + (f" (survey mapped at {sc['mapping_fps']:g})" if sc.get("mapping_fps", sc["fps"]) != sc["fps"] else "")
        + f", seeds {sc['seeds']}",
        table,
        f"availability (frames with a whole cube in view that got a fix): {_fmt(fx['availability'])}"
        f"   fixes over 0.5 m: {fx['over_0_5m']}",
        f"filter: NEES {_fmt(fu['nees_mean'])} (2 expected), true error inside the reported 3 sigma "
        f"{_fmt(fu['within_3sigma'])}; fixes gated {summary['gate']['rejected']}, accepted over 0.5 m "
        f"{summary['gate']['accepted_over_0_5m']} (largest {_fmt(summary['gate']['accepted_max_m'], ' m')}),"
        f" re-initialisations {summary['gate']['reinitialisations']}; "
        f"GPS-denied {summary['denied_s']:.0f} s"
        + (f" at {_heights(summary['height_agl'])} above the ground" if summary.get("height_agl") else ""),
        f"GPS_INPUT while denied: 3D fix {_fmt(summary['gps_input']['fix_3d_share'])} of {summary['gps_input']['outputs']}"
        f" outputs, their true error inside 3x the reported accuracy {_fmt(summary['gps_input']['within_3_reported'])}",
        f"dead reckoning: longest stretch without an accepted fix {_fmt(fu['longest_gap_s'], ' s', 1)}; the fused maximum"
        f" came {_fmt(fu['since_fix_at_max_s'], ' s', 1)} after one; velocity error as {fu['long_gaps']['count']} stretches"
        f" of {fu['long_gaps']['min_s']:g} s or more began: RMS {_fmt(fu['long_gaps']['velocity_error_rms_m_s'], ' m/s')},"
        f" max {_fmt(fu['long_gaps']['velocity_error_max_m_s'], ' m/s')}",
        f"thesis-style mission averages: landmark {_fmt(ma['landmark_m'], ' m')}, position {_fmt(ma['position_m'], ' m')}",
        f"time per frame: median {_fmt(ms['median'], ' ms')}, p99 {_fmt(ms['p99'], ' ms')}"
        f" (features per frame: {_fmt(summary['features_per_frame_median'], '', 0)})",
    ]
    if summary.get("featureless"):
        f = summary["featureless"]
        lines.append(
            f"featureless ground: {f['crossings']} crossing(s), {f['seconds_over']:.0f} s over it; accepted fixes there"
            f" {f['accepted_fixes']} (max {_fmt(f['accepted_fix_max_m'], ' m')}); outputs inside 3x the reported accuracy"
            f" {_fmt(f['within_3_reported'])}; GPS_INPUT said no fix in {f['said_no_fix']} crossing(s), at most"
            f" {_fmt(f['no_fix_after_s'], ' s', 1)} after entering, and had a 3D fix again at most"
            f" {_fmt(f['fix_3d_again_s'], ' s', 1)} after leaving"
        )
    if summary.get("blackout"):
        b = summary["blackout"]
        lines.append(
            f"camera blackout: {b['outputs_during']} outputs during it, reported accuracy {_fmt(b['sigma_before_m'])} m"
            f" before, {_fmt(b['sigma_at_end_m'])} m at its end; true error at its end {_fmt(b['error_at_end_m'])} m;"
            f" recovered {_fmt(b['recovery_s'])} s after"
        )
    return "\n".join(lines)


def _eval(args) -> int:
    import dataclasses

    from auxgps.evaluation.driver import MissionRun, evaluate
    from auxgps.sim.faults import load_fault_plan
    from auxgps.sim.flight import load_sim_config

    if args.altitude is None and not args.mission:
        raise ConfigError("--altitude is needed without --mission (a mission may fly its own heights)")
    if args.map and not args.mission:
        raise ConfigError("--map goes with --mission: the estimator of a mission starts from these maps")
    if bool(args.mission) != (args.gps_lost_at_waypoint is not None):
        raise ConfigError("--mission and --gps-lost-at-waypoint go together: the mission, and the item GPS1 is lost at")
    sim = load_sim_config(args.sim_config)
    if args.faults:
        sim = dataclasses.replace(sim, faults=list(load_fault_plan(args.faults).faults))
    summary = evaluate(
        args.world,
        args.altitude,
        fps=args.fps,
        mapping_fps=args.mapping_fps,
        runs=args.runs,
        seed=args.seed,
        pipeline=load_pipeline_config(args.config),
        sim=sim,
        workers=args.workers,
        progress=not args.quiet,
        mission=MissionRun(args.mission, args.speed_m_s, args.gps_lost_at_waypoint, tuple(args.map or ())) if args.mission else None,
        ray=args.ray,
    )
    print(summary_table(summary))
    for t_s, line in summary["notes"][:40]:
        print(f"  {t_s:7.2f} s  {line}")
    _write_json(args.json, summary)
    return 0


def _write_json(path: str | None, figures: dict) -> None:
    if path:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(path).write_text(json.dumps(figures, indent=2))
        print(f"wrote {path}")


def _demo(args) -> int:
    from auxgps.demo import run_demo

    if bool(args.mission) != (args.gps_lost_at_waypoint is not None):
        raise ConfigError("--mission and --gps-lost-at-waypoint go together: the mission, and the item GPS1 is lost at")
    mission = ("--mission", args.mission, "--speed-m-s", str(args.speed_m_s), "--gps-lost-at-waypoint",
               str(args.gps_lost_at_waypoint)) if args.mission else ()
    if mission:
        print(f"auxgps demo: the vehicle emulator flies {args.mission} over {args.world}; GPS1 fails on reaching item "
              f"{args.gps_lost_at_waypoint};")
    else:
        print(f"auxgps demo: the vehicle emulator flies a survey over {args.world}; GPS1 fails after 60 s;")
    print("auxgps, a separate process on loopback, keeps the autopilot flying on GPS2. A control run flies without auxgps.")
    figures = run_demo(args.world, out_dir=args.out_dir, mission=mission, sim_camera_fps=args.sim_camera_fps)
    print(json.dumps(figures, indent=2))
    print(f"report: {args.out_dir}/report.png, {args.out_dir}/report.json")
    _write_json(args.json, figures)
    return 0


def _run(args) -> int:
    import logging

    from auxgps.companion import Companion, RunOptions

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")

    def stop(signum, frame):  # SIGTERM ends the flight like Ctrl-C: logs closed, map saved
        raise KeyboardInterrupt

    # SIGINT explicitly too: started in the background by a non-interactive shell, a process inherits SIGINT
    # ignored, and Ctrl-C or a supervisor's interrupt would then not end the flight.
    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, stop)
    opts = RunOptions(
        connect=args.connect,
        camera=args.camera,
        map_in=args.map,
        map_out=args.save_map,
        log_dir=args.log_dir,
        duration_s=args.duration,
        gps_input_rate_hz=args.rate,
        gps_delay_s=args.gps_delay_ms / 1000.0,
        gps1_lag_s=args.gps1_lag_ms / 1000.0,
        record_dir=args.record,
        connect_timeout_s=args.connect_timeout,
        checkpoint_s=args.checkpoint,
        frame_nice=args.nice,
        take_primary_on_drift=args.take_primary_on_drift,
        stall_report_s=args.stall_report,
        sim_camera_fps=args.sim_camera_fps,
    )
    return Companion(load_pipeline_config(args.config), opts).run()


def _replay(args) -> int:
    from auxgps.replay import plot_report, public, replay, score, score_lines, write_trajectories

    out_dir = Path(args.out) if args.out else Path(args.recording) / "replay"
    pipeline = load_pipeline_config(args.config) if args.config else None
    result = replay(args.recording, out_dir, deny_gps_after_s=args.deny_gps_after, pipeline=pipeline)
    for line in result.problems:
        print(f"auxgps: replay: {line}", file=sys.stderr)
    print(f"replayed {result.n_messages} messages, {result.n_frames} frames, {result.n_outputs} GPS_INPUT; logs in {out_dir}")
    figures = {"messages": result.n_messages, "frames": result.n_frames, "gps_input": result.n_outputs, "problems": result.problems}
    if args.deny_gps_after is not None:
        from auxgps.io.recording import open_recording

        lag_s = float(open_recording(args.recording).meta.get("options", {}).get("gps1_lag_s", 0.1))
        scored = score(result, lag_s)
        for line in score_lines(scored):
            print(line)
        if scored.get("scored"):
            files = write_trajectories(scored, out_dir, result.clock_offset_s, result.frame)
            print("trajectories: " + ", ".join(str(f) for f in files))
            if args.report:
                Path(args.report).parent.mkdir(parents=True, exist_ok=True)
                plot_report(scored, args.report)
                print(f"report: {args.report}")
        figures["score"] = public(scored)
    _write_json(args.json, figures)
    return 0


def _delay_ms(text):
    value = int(text)
    if not 1 <= value <= 250:
        raise argparse.ArgumentTypeError(f"must be 1 to 250 ms (ArduPilot's GPS2_DELAY_MS range), got {text}")
    return value


_THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS", "VECLIB_MAXIMUM_THREADS")


def _bench(args) -> int:
    import os

    if args.argv is not None and any(os.environ.get(k) != "1" for k in _THREAD_ENV):
        # BLAS reads its thread count when NumPy is first imported, which has happened: start again with it set.
        env = dict(os.environ, **{k: "1" for k in _THREAD_ENV})
        os.execvpe(sys.executable, [sys.executable, "-m", "auxgps.cli", *args.argv], env)
    import time

    from auxgps.evaluation.bench import BenchConfig, bench_report, machine_info, reference_ms, run_bench, tiny_sim_config
    from auxgps.sim.flight import load_sim_config

    sim = load_sim_config(args.sim_config)
    sizes = args.map_sizes
    if args.tiny:
        sim = tiny_sim_config(sim)
        sizes = sizes or (5_000, 20_000)
    sizes = sizes or BenchConfig.map_sizes
    reported = args.reported_map or (100_000 if 100_000 in sizes else sizes[len(sizes) // 2])
    cfg = BenchConfig(alt_m=args.altitude, fps=args.fps, mapping_fps=args.mapping_fps, seed=args.seed, map_sizes=sizes, reported_map=reported,
                      world=args.world)
    methods = () if args.no_baseline else (_load_baseline(load_pipeline_config(args.config)),)
    t0 = time.monotonic()

    def progress(msg=None):
        if msg and not args.quiet:
            print(f"[{time.monotonic() - t0:6.1f} s] {msg}", file=sys.stderr, flush=True)

    pipeline = load_pipeline_config(args.config)
    if args.render_only:
        import cv2

        cv2.setNumThreads(1)
        figures = {"machine": dict(machine_info(), reference_ms=reference_ms())}
    else:
        figures = run_bench(pipeline, sim, cfg, tuple(m for m in methods if m is not None), progress)
        print(bench_report(figures))
    if args.tiny or args.no_render:
        figures["ortho_render"] = {"skipped": "--tiny" if args.tiny else "--no-render"}
    else:
        from auxgps.core.camera import camera_from_config
        from auxgps.evaluation.render_bench import render_bench_report, run_render_bench

        figures["ortho_render"] = run_render_bench(camera_from_config(pipeline.camera), args.render_cache, progress=progress)
        print(render_bench_report(figures["ortho_render"]))
    _write_json(args.json, figures)
    return 0


def _load_baseline(pipeline):
    """The thesis' method (auxgps.evaluation.thesis_baseline), run beside ours on the benchmark's frames."""
    from auxgps.core.camera import camera_from_config
    from auxgps.evaluation.thesis_baseline import make_baseline

    return make_baseline(camera_from_config(pipeline.camera))


def _camera_calibrate(args) -> int:
    import numpy as np
    import yaml

    from auxgps.core.calibration import calibrate, find_board
    from auxgps.io.camera import calibration_images

    cols, rows = args.board
    views, size, n_seen, last = [], None, 0, None
    for name, gray in calibration_images(video=args.video, images=args.images):
        n_seen += 1
        if size is None:
            size = gray.shape[::-1]
        elif gray.shape[::-1] != size:
            raise ConfigError(f"{name}: {gray.shape[1]}x{gray.shape[0]} px, where the first view was {size[0]}x{size[1]}")
        corners = find_board(gray, cols, rows)
        if corners is None:
            continue
        if last is not None and np.mean(np.linalg.norm(corners - last, axis=1)) < args.min_move_px:
            continue  # the board has hardly moved since the last view kept: nothing new
        views.append(corners)
        last = corners
        if len(views) >= args.max_views:
            break
    print(f"auxgps camera calibrate: the {cols}x{rows} board found in {len(views)} of {n_seen} views")
    cal = calibrate(views, *(size or (0, 0)), cols, rows, args.square_mm / 1000.0, free_k3=args.k3)
    worst = int(np.argmax(cal.per_view_rms_px))
    print(f"reprojection RMS {cal.rms_px:.3f} px (worst view {cal.per_view_rms_px[worst]:.3f} px); focal {cal.K[0, 0]:.1f} x {cal.K[1, 1]:.1f} px, "
          f"centre {cal.K[0, 2]:.1f}, {cal.K[1, 2]:.1f} px; k1 {cal.dist[0]:+.4f} k2 {cal.dist[1]:+.4f} p1 {cal.dist[2]:+.5f} "
          f"p2 {cal.dist[3]:+.5f} k3 {cal.dist[4]:+.4f}")
    if cal.rejected:
        print(f"  {len(cal.rejected)} view(s) fitted much worse than the rest and were left out")
    if cal.rms_px > 1.0:
        print("  note: over 1 px is a poor calibration (a blurred or bent board, or views too alike); take new views")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    head = (f"# auxgps camera calibrate: {cal.n_views} views of a {cols}x{rows} board, {args.square_mm:g} mm squares; "
            f"reprojection RMS {cal.rms_px:.3f} px.\n# Use it as a pipeline configuration (--config) or paste its camera: section "
            "into yours. The mount (camera: body to camera) is the mount: section, which this file does not set.\n")
    out.write_text(head + yaml.safe_dump({"camera": cal.camera_section()}, sort_keys=False, default_flow_style=None))
    print(f"wrote {out}")
    return 0


def _check(args) -> int:
    from auxgps import preflight

    wanted = preflight.load_wanted()
    print(f"auxgps check: {args.connect} against {preflight.PARM_FILE.name}, auxgps's GPS delay {args.gps_delay_ms} ms")
    ap = preflight.connect(args.connect, args.timeout)
    findings = check_and_print(preflight, ap, wanted, args)
    bad = [f for f in findings if not f.ok]
    fixable = [f for f in bad if f.set_params]
    if args.fix and fixable:
        names = ", ".join(n for f in fixable for n in f.set_params)
        if not args.yes:
            answer = input(f"write {names} to the autopilot? [y/N] ").strip().lower()
            if answer not in ("y", "yes"):
                print("nothing written")
                return 1
        for line in preflight.fix(ap, fixable):
            print(line)
        if args.reboot:
            preflight.reboot(ap)
            print("reboot asked for; run auxgps check again once the autopilot is back")
            return 0
        print("after writing:")
        findings = check_and_print(preflight, ap, wanted, args)
        bad = [f for f in findings if not f.ok]
    print("all green" if not bad else f"{len(bad)} to put right" + ("" if args.fix else " (--fix writes the parameters)"))
    return 0 if not bad else 1


def check_and_print(preflight, ap, wanted, args):
    from auxgps.core.autopilot_setup import check_setup

    findings = check_setup(preflight.observe(ap, wanted, args.listen), wanted, args.gps_delay_ms)
    for f in findings:
        print(f"  {'ok ' if f.ok else 'BAD'}  {f.text}")
    return findings


def _board(text):
    try:
        cols, rows = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected COLSxROWS, the board's inner corners, such as 9x6; got {text!r}") from None
    if cols < 3 or rows < 3:
        raise argparse.ArgumentTypeError(f"a board needs at least 3x3 inner corners, got {text!r}")
    return cols, rows


def _photo_settings(args):
    from auxgps.config import load_photo_camera, load_photo_config

    cfg = load_photo_config(args.config)
    if args.max_side is not None:
        from dataclasses import replace

        cfg = replace(cfg, max_side_px=args.max_side)
    return (load_photo_camera(args.camera) if args.camera else None), cfg


def _map_build(args) -> int:
    if args.orthophoto:
        return _map_build_orthophoto(args)
    from auxgps.io.map_file import save_photo_map
    from auxgps.io.photos import list_photos
    from auxgps.photo_workflow import build_map_from_photos

    if not args.images:
        raise ConfigError("auxgps map build: --images DIR (photos) or --orthophoto ORTHO.tif is needed")
    cam_cfg, cfg = _photo_settings(args)
    files = list_photos(args.images, args.only)
    print(f"auxgps map build: {len(files)} photos from {args.images}")
    report = build_map_from_photos(files, cam_cfg, cfg, progress=None if args.quiet else lambda name: print(f"  features: {name}", flush=True))
    for msg in report.messages:
        print(f"  note: {msg}")
    pm = report.photo_map
    save_photo_map(args.out, pm, report.frame)
    res = [p.gps_residual_ne_m for p in pm.photos if p.gps_residual_ne_m is not None]
    rms = float(np.sqrt(np.mean(np.sum(np.square(res), axis=1)))) if res else float("nan")
    print(f"map: {len(pm)} points from {len(pm.photos)} photos; photo positions vs their GPS: RMS {rms:.2f} m; "
          f"map placement one sigma {pm.georef_sigma_h_m:.2f} m")
    for cid, cam in pm.cameras.items():
        print(f"camera {cid}: focal {cam.focal_px:.1f} px, k1 {cam.dist[0]:+.4f}, k2 {cam.dist[1]:+.4f}")
    print(f"wrote {args.out}")
    return 0


def _map_build_orthophoto(args) -> int:
    from auxgps.core.landmarks import LandmarkMap
    from auxgps.core.prior_map import FLIGHT
    from auxgps.io.map_file import save_map, save_photo_map
    from auxgps.ortho_map import build_prior_map
    from auxgps.photo.types import PhotoMap

    if args.images:
        raise ConfigError("auxgps map build: --images and --orthophoto are two ways to build a map: give one")
    pipeline = photo_cfg = None
    if args.descriptor == "orb":
        pipeline = load_pipeline_config(args.pipeline)
    else:
        _, photo_cfg = _photo_settings(args)
    print(f"auxgps map build: {args.descriptor} landmarks from the orthophoto {args.orthophoto}")
    report = build_prior_map(args.orthophoto, descriptor=args.descriptor, pipeline=pipeline, photo_cfg=photo_cfg,
                             gsd_m=args.gsd_m, dsm_path=args.dsm, ground_alt_amsl_m=args.ground_alt_m,
                             georef_sigma_m=args.georef_sigma_m, tile_px=args.tile_px,
                             progress=None if args.quiet else lambda msg: print(f"  {msg}", flush=True))
    for msg in report.messages:
        print(f"  note: {msg}")
    c, f = report.columns, report.frame
    if report.descriptor == "orb":
        lm = LandmarkMap.from_columns({**c, "source": np.ones(report.count, np.uint8)}, sources=[FLIGHT, report.source])
        save_map(args.out, lm, f, prior=report.prior)
        lo, hi = report.prior["gsd_m"] * report.prior["focal_px"] * np.array(
            [pipeline.positioning.min_detection_scale, pipeline.detector.scale_factor])
        use = f"for auxgps run; frames are matched at this scale from {lo:.0f} m to {hi:.0f} m above ground (camera focal {report.prior['focal_px']:.0f} px)"
    else:
        from auxgps.core.landmarks import unpack_sym

        pm = PhotoMap(p_ned_m=c["p_ned_m"].astype(float), info_ned=unpack_sym(c["info_packed"].astype(float)),
                      descriptors=c["descriptors"], n_views=np.ones(report.count, int), cameras={},
                      georef_sigma_h_m=report.source.georef_sigma_h_m, photos=(),
                      source=np.zeros(report.count, np.uint8), sources=(report.source,))
        save_photo_map(args.out, pm, f, prior=report.prior)
        use = "for auxgps locate"
    print(f"map: {report.count} landmarks from {report.tiles} tiles at {report.gsd_m:.3f} m per pixel (the file's "
          f"{report.prior['file_gsd_m']:.3f} m), {use}; heights: {report.heights}; placement one sigma "
          f"{report.source.georef_sigma_h_m:.2f} m; origin {f.lat_deg:.7f} {f.lon_deg:.7f} {f.alt_amsl_m:.1f} m")
    print(f"wrote {args.out}")
    return 0


def _ortho_build(args) -> int:
    from auxgps.io.photos import list_photos
    from auxgps.photo_workflow import build_orthophoto

    cam_cfg, cfg = _photo_settings(args)
    files = list_photos(args.images, args.only)
    print(f"auxgps ortho build: {len(files)} photos from {args.images}")
    report = build_orthophoto(files, cam_cfg, cfg, args.out, gsd_m=args.gsd_m,
                              progress=None if args.quiet else lambda msg: print(f"  {msg}", flush=True))
    for msg in report.messages:
        print(f"  note: {msg}")
    p = report.plane
    print(f"orthophoto: {report.width_px} x {report.height_px} px at {report.gsd_m:.4f} m, {report.crs}, "
          f"{len(report.used)} photos; ground plane: points' scatter about it {p.rms_m:.2f} m RMS ({p.n_points} points)")
    s = report.seam_summary()
    if s["pairs"]:
        print(f"seams between neighbouring photos ({s['pairs']} pairs): median {s['median_m']:.3f} m, "
              f"95th percentile {s['p95_m']:.3f} m, max {s['max_m']:.3f} m")
    else:
        print("seams: no neighbouring pair could be measured")
    print(f"wrote {args.out} and {report.path.with_suffix('.json')}")
    return 0


def _locate(args) -> int:
    from auxgps.io.map_file import load_photo_maps
    from auxgps.io.photos import list_photos
    from auxgps.photo_workflow import locate_photos

    cam_cfg, cfg = _photo_settings(args)
    photo_map, frame = load_photo_maps(args.map)
    files = list_photos(args.images, args.only)

    def show(row):
        if row["located"]:
            err = "-" if row["error_m"] is None else f"{row['error_m']:.2f} m"
            line = (f"{row['file']}: {row['lat_deg']:.7f} {row['lon_deg']:.7f}  accuracy {row['accuracy_m']:.2f} m  "
                    f"inliers {row['inliers']}  distance to its GPS {err}")
            if row.get("map"):
                line += f"  on {row['map']}"
        else:
            line = f"{row['file']}: {row['message']}"
        for note in row["notes"]:
            line += f"  [{note}]"
        print(line, flush=True)

    result = locate_photos(files, photo_map, frame, cam_cfg, cfg, use_metadata=not args.ignore_metadata, progress=show)
    sm = result["summary"]
    med = "-" if sm["median_error_m"] is None else f"{sm['median_error_m']:.2f} m"
    mx = "-" if sm["max_error_m"] is None else f"{sm['max_error_m']:.2f} m"
    print(f"located {sm['located']} of {sm['total']}; distance to their own GPS: median {med}, max {mx}")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(result, indent=2))
        print(f"wrote {args.json}")
    return 0


def _number(kind, accept, wanted: str):
    """An argparse type: ``kind`` (int or float) parsed, and refused unless ``accept(value)``, saying ``wanted``."""

    def parse(text):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a {'whole ' if kind is int else ''}number, got {text!r}") from None
        if not accept(value):
            raise argparse.ArgumentTypeError(f"must be {wanted}, got {text}")
        return value

    return parse


def _positive(kind):
    return _number(kind, lambda v: v > 0, "positive")


def _link_url(text):
    from auxgps.errors import LinkError
    from auxgps.io.link import parse_link_url

    try:
        parse_link_url(text)
    except LinkError as err:
        raise argparse.ArgumentTypeError(str(err).removeprefix(f"--connect {text!r}: ")) from None
    return text


def _counts(text):
    """Comma-separated positive whole numbers (landmark counts)."""
    try:
        values = tuple(int(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected whole numbers separated by commas, such as 10000,100000; got {text!r}") from None
    if any(v <= 0 for v in values):
        raise argparse.ArgumentTypeError(f"every count must be positive, got {text!r}")
    return values


def _non_negative(kind):
    return _number(kind, lambda v: v >= 0, "zero or more")


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("auxgps")
    except PackageNotFoundError:
        return "(not installed)"


class _Parser(argparse.ArgumentParser):
    """A usage mistake is one line naming the argument, and exit code 2 (argparse would print the usage too)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="auxgps", description="A visual back-up GPS for drones.")
    parser.add_argument("--version", action="version", version=f"auxgps {_version()}")
    sub = parser.add_subparsers(dest="command", required=True)

    def add_eval_options(p):
        p.add_argument("--fps", type=_positive(float), default=2.0, help="camera frames per second (default 2)")
        p.add_argument("--mapping-fps", type=_positive(float), help="frames per second mapped in the survey (default: --fps)")
        p.add_argument("--seed", type=int, default=1, help="seed of the first run (default 1)")
        p.add_argument("--config", help="pipeline config YAML (default: built-in defaults)")
        p.add_argument("--sim-config", help="simulation config YAML (default: built-in defaults)")
        p.add_argument("--json", help="write the figures as JSON to this file")
        p.add_argument("--workers", type=_positive(int), help="parallel processes (default: one per core)")
        p.add_argument("--ray", metavar="ADDRESS", help="run the runs on a Ray cluster instead ('auto', 'local' to start one "
                                                       "here, or host:port; pip install 'auxgps[cluster]')")
        p.add_argument("--quiet", action="store_true", help="no progress bar")

    p = sub.add_parser("eval", help="fly a mapping survey then a positioning flight over a simulated world; score them")
    p.add_argument("--world", required=True, help="a world by name (one_cube_1m, cubes4_0.5m_different, ...) or a world YAML file")
    p.add_argument("--altitude", type=_positive(float), help="survey height above ground, m (with --mission: every height of "
                                                                "the mission at this, default its own heights)")
    p.add_argument("--runs", type=_positive(int), default=1, help="seeded runs (default 1)")
    p.add_argument("--faults", help="a YAML list of faults to inject into the positioning flight (auxgps/sim/faults.py; "
                                    "config/faults/all.yaml has one of each)")
    p.add_argument("--mission", help="fly this mission (.waypoints, QGC WPL 110, or a QGroundControl .plan) once instead: "
                                     "mapping with GPS1, GPS1 lost at --gps-lost-at-waypoint, the rest scored")
    p.add_argument("--speed-m-s", type=_positive(float), default=5.0, help="with --mission: its speed, m/s (default 5)")
    p.add_argument("--map", action="append", help="with --mission: start from this map (a prior map from auxgps map build "
                                                  "--orthophoto, or a flight's); repeatable")
    p.add_argument("--gps-lost-at-waypoint", type=_positive(int), help="with --mission: the item (its number in the file, "
                                                                       "home being 0) on reaching which GPS1 is lost")
    add_eval_options(p)
    p.set_defaults(func=_eval)

    p = sub.add_parser("run", help="the companion process: MAVLink to ArduPilot, camera in, GPS_INPUT out as GPS2")
    p.add_argument("--connect", required=True, type=_link_url,
                   help="the autopilot: tcp:127.0.0.1:5762, udpin:0.0.0.0:14550, or a serial device and baud rate, /dev/ttyAMA0,921600")
    p.add_argument("--connect-timeout", type=_positive(float), default=15.0,
                   help="at start, give up after this many seconds without a connection (default 15)")
    p.add_argument("--camera", required=True, help="sim:WORLD.yaml (rendered at the simulator's truth), a video file, or a device index")
    p.add_argument("--sim-camera-fps", type=_positive(float), metavar="F",
                   help="with --camera sim:WORLD, render F frames a second in a thread of its own, as a camera delivers "
                        "(frames the loop cannot take are dropped, the newest kept); default: one frame per loop")
    p.add_argument("--config", help="pipeline config YAML")
    p.add_argument("--map", action="append",
                   help="load this map file at start (it must exist and be readable): a flight's, or a prior map from "
                        "auxgps map build --orthophoto; repeat to load several at once")
    p.add_argument("--save-map", help="save the map here, atomically: while flying (see --checkpoint), at every mode change and at the end")
    p.add_argument("--checkpoint", type=_non_negative(float), default=10.0, metavar="S",
                   help="with --save-map, write the map every S seconds while flying (default 10; 0: at mode changes and the end only)")
    p.add_argument("--nice", type=_number(int, lambda v: 0 <= v <= 19, "0 to 19"), default=0, metavar="N",
                   help="run frame processing N niceness steps below the GPS_INPUT timer and the link reader, so that a "
                        "busy computer delays frames (dropped, newest kept) before GPS_INPUT (default 0; see docs/faults.md)")
    p.add_argument("--stall-report", type=_non_negative(float), default=0.5, metavar="S",
                   help="the GPS_INPUT timer held up over S seconds: every thread's stack at that moment to stalls.txt "
                        "in --log-dir, and an event (default 0.5; 0: off)")
    p.add_argument("--take-primary-on-drift", action="store_true",
                   help="opt-in: while GPS1 is found dragged away from the map, make GPS2 the autopilot's primary "
                        "(GPS_AUTO_SWITCH 0, GPS_PRIMARY 1; restored after). Read the README's risks first")
    p.add_argument("--log-dir", default="out/run", help="CSV logs of fixes, gate decisions, GPS_INPUT and events")
    p.add_argument("--duration", type=_positive(float), help="stop after this many seconds")
    p.add_argument("--rate", type=_positive(float), default=10.0, help="GPS_INPUT rate, Hz (default 10)")
    p.add_argument("--gps-delay-ms", type=_delay_ms, default=100,
                   help="each GPS_INPUT describes the vehicle this long before it is sent; set the autopilot's GPS2_DELAY_MS to the same (default 100)")
    p.add_argument("--gps1-lag-ms", type=_delay_ms, default=100,
                   help="how old a GPS1 reading is when the autopilot gets it (GPS_RAW_INT's fix time): its receiver's lag (default 100, as ArduPilot SITL's SIM_GPS1_LAG_MS)")
    p.add_argument("--record", metavar="DIR", help="record what auxgps sees (tlog, frames, journal, config, map) into DIR, for auxgps replay")
    p.set_defaults(func=_run)

    p = sub.add_parser("replay", help="run auxgps on a recorded flight; with --deny-gps-after, score it against the GPS1 it hides")
    p.add_argument("recording", help="a folder written by auxgps run --record")
    p.add_argument("--deny-gps-after", type=_non_negative(float), metavar="S", help="hide GPS1 from S seconds after the recording's start; score against it")
    p.add_argument("--config", help="pipeline config YAML (default: the one the flight ran with)")
    p.add_argument("--out", help="folder for the replay's logs and trajectories (default: RECORDING/replay)")
    p.add_argument("--json", help="write the figures as JSON to this file")
    p.add_argument("--report", metavar="OUT.png", help="write a PNG report (track, estimate, error over time)")
    p.set_defaults(func=_replay)

    p = sub.add_parser("bench", help="time the pipeline per frame on one thread, with maps up to a million landmarks, beside the thesis' method")
    p.add_argument("--json", help="write the figures as JSON to this file")
    p.add_argument("--config", help="pipeline config YAML (default: built-in defaults)")
    p.add_argument("--sim-config", help="simulation config YAML (default: built-in defaults); its surveys are the flights timed")
    p.add_argument("--world", help="a world by name or YAML file (an orthophoto world, say) instead of the seeded gravel and four cubes")
    p.add_argument("--altitude", type=_positive(float), default=15.0, help="height of both flights above the ground, m (default 15)")
    p.add_argument("--fps", type=_positive(float), default=2.0, help="frames per second of the positioning flight (default 2)")
    p.add_argument("--mapping-fps", type=_positive(float), default=1.0, help="frames per second of the mapping survey (default 1)")
    p.add_argument("--seed", type=int, default=1, help="seed of the world, flights and padding (default 1)")
    p.add_argument("--map-sizes", type=_counts, help="landmark counts to pad the map to, comma-separated (default 10000,100000,1000000)")
    p.add_argument("--reported-map", type=_positive(int), help="the map size of the headline positioning figures (default: the second size)")
    p.add_argument("--tiny", action="store_true", help="a survey of a few metres and small maps: a smoke test of seconds")
    p.add_argument("--no-baseline", action="store_true", help="do not run the thesis' method beside")
    p.add_argument("--render-only", action="store_true", help="only the orthophoto world's rendering case (a 2 km square 5 cm GeoTIFF, built once)")
    p.add_argument("--no-render", action="store_true", help="without the orthophoto world's rendering case")
    p.add_argument("--render-cache", metavar="DIR", help="folder for the rendering case's GeoTIFFs (default ~/.cache/auxgps/bench; about 1 GB)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.set_defaults(func=_bench)

    def add_photo_options(p, images_required=True):
        p.add_argument("--images", required=images_required, help="folder of photos (JPEG, PNG, TIFF)")
        p.add_argument("--only", action="append", help="only photos whose file name matches this glob (repeatable, or comma-separated)")
        p.add_argument("--camera", help="camera file (config/cameras/*.yaml); default: from EXIF, refined by map building")
        p.add_argument("--config", help="photo workflow settings YAML (default: built-in defaults)")
        p.add_argument("--max-side", type=_non_negative(int), help="reduce photos to this longer side, px, for features (0: full resolution)")
        p.add_argument("--quiet", action="store_true", help="no progress lines")

    p = sub.add_parser("map", help="landmark maps from photos")
    map_sub = p.add_subparsers(dest="map_command", required=True)
    p = map_sub.add_parser("build", help="build a landmark map from a folder of geotagged photos, or from an orthophoto")
    add_photo_options(p, images_required=False)
    p.add_argument("--out", required=True, help="map file to write (.npz)")
    p.add_argument("--orthophoto", metavar="ORTHO.tif", help="a prior map from this georeferenced orthophoto (any CRS), not from photos")
    p.add_argument("--descriptor", choices=("orb", "sift"), default="orb",
                   help="with --orthophoto: orb for auxgps run, sift for auxgps locate (default orb)")
    p.add_argument("--pipeline", metavar="PIPELINE.yaml",
                   help="with --orthophoto and orb: the flight's pipeline settings (its camera and detector), as auxgps run --config takes them")
    p.add_argument("--dsm", metavar="DSM.tif", help="with --orthophoto: heights from this height model (m above mean sea level)")
    p.add_argument("--ground-alt-m", type=float, help="with --orthophoto and no --dsm: the ground's height, m above mean sea level")
    p.add_argument("--gsd-m", type=_positive(float), help="with --orthophoto: build at this many metres a pixel (default: the file's)")
    p.add_argument("--georef-sigma-m", type=_non_negative(float),
                   help="with --orthophoto: its placement error, one sigma, m (default: its own tag, else 2)")
    p.add_argument("--tile-px", type=_positive(int), help="with --orthophoto: detect in tiles of this side, px (default: half a frame for orb)")
    p.set_defaults(func=_map_build)

    p = sub.add_parser("ortho", help="orthophotos from photos")
    ortho_sub = p.add_subparsers(dest="ortho_command", required=True)
    p = ortho_sub.add_parser("build", help="an orthophoto GeoTIFF from a folder of geotagged photos (a world's ground)")
    add_photo_options(p)
    p.add_argument("--out", required=True, help="GeoTIFF to write (ORTHO.tif; the report goes to ORTHO.json)")
    p.add_argument("--gsd-m", type=_positive(float), help="metres a pixel (default: the photos' median ground sample distance)")
    p.set_defaults(func=_ortho_build)

    p = sub.add_parser("locate", help="locate photos from a map alone; their own GPS only scores the answer")
    p.add_argument("--map", required=True, action="append",
                   help="map file from auxgps map build (from photos, or --orthophoto with --descriptor sift); repeat to use several at once")
    add_photo_options(p)
    p.add_argument("--json", help="write per-photo results and a summary as JSON to this file")
    p.add_argument("--ignore-metadata", action="store_true", help="use no attitude or height metadata of the photos")
    p.set_defaults(func=_locate)

    p = sub.add_parser("check", help="pre-flight: the autopilot's firmware, parameters, streams and GPS1, for auxgps as GPS2")
    p.add_argument("--connect", required=True, type=_link_url, help="the autopilot, as for auxgps run")
    p.add_argument("--gps-delay-ms", type=_delay_ms, default=100, help="auxgps run's --gps-delay-ms (default 100): GPS2_DELAY_MS must equal it")
    p.add_argument("--fix", action="store_true", help="write the parameter file's values for what is wrong (asks first)")
    p.add_argument("--yes", action="store_true", help="with --fix: do not ask")
    p.add_argument("--reboot", action="store_true", help="with --fix: reboot the autopilot after writing")
    p.add_argument("--timeout", type=_positive(float), default=15.0, help="seconds to wait for the autopilot (default 15)")
    p.add_argument("--listen", type=_positive(float), default=3.0, help="seconds to measure the streams over (default 3)")
    p.set_defaults(func=_check)

    p = sub.add_parser("camera", help="the camera: calibration")
    cam_sub = p.add_subparsers(dest="camera_command", required=True)
    p = cam_sub.add_parser("calibrate", help="intrinsics and distortion from views of a chessboard; writes the camera file")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--video", help="a video of the board moved about in front of the camera (one view per 0.5 s)")
    src.add_argument("--images", help="a folder of images of the board")
    p.add_argument("--board", type=_board, required=True, metavar="COLSxROWS", help="the board's inner corners, such as 9x6")
    p.add_argument("--square-mm", type=_positive(float), required=True, help="the side of one square, mm")
    p.add_argument("--out", required=True, metavar="CAMERA.yaml", help="the camera file to write")
    p.add_argument("--max-views", type=_positive(int), default=40, help="use at most this many views (default 40)")
    p.add_argument("--k3", action="store_true", help="fit the third radial term too (fish-eye-like lenses only)")
    p.add_argument("--min-move-px", type=_non_negative(float), default=20.0,
                   help="skip a view whose corners moved less than this since the last one kept, px (default 20)")
    p.set_defaults(func=_camera_calibrate)

    p = sub.add_parser("demo", help="closed loop: the vehicle emulator and auxgps run, GPS1 failing mid-survey")
    p.add_argument("--out-dir", default="out/demo", help="logs, report.png and report.json go here")
    p.add_argument("--world", default=DEMO_WORLD, help=f"a world by name or a world YAML file (default {DEMO_WORLD})")
    p.add_argument("--mission", help="fly this mission instead of the survey (.waypoints or .plan), at its own heights")
    p.add_argument("--speed-m-s", type=_positive(float), default=5.0, help="with --mission: its speed, m/s (default 5)")
    p.add_argument("--gps-lost-at-waypoint", type=_positive(int), help="with --mission: the item on reaching which GPS1 fails")
    p.add_argument("--sim-camera-fps", type=_positive(float), metavar="F",
                   help="the simulated camera delivers F frames a second, as a real one does (default: one per frame loop); "
                        "the report's frames say how many were processed and dropped, and the capture to GPS_INPUT time")
    p.add_argument("--json", help="also write the figures here")
    p.set_defaults(func=_demo)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    args.argv = None if argv is not None else sys.argv[1:]  # a command-line run, which bench may start again
    try:
        return args.func(args)
    except AuxGpsError as err:
        print(f"auxgps: error: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("auxgps: interrupted", file=sys.stderr)
        return 130
    except Exception as err:  # noqa: BLE001 - anything else is a bug: say so, keep the traceback, exit 3
        return _report_bug(err)


EXIT_BUG = 3


def _report_bug(err: Exception) -> int:
    import tempfile
    import time
    import traceback

    path = Path(tempfile.gettempdir()) / f"auxgps-crash-{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}.log"
    try:
        path.write_text(f"auxgps {sys.argv[1:]}\n" + "".join(traceback.format_exception(err)))
        where = f"the traceback is in {path}"
    except OSError:
        where = "the traceback could not be written"
    print(f"auxgps: internal error, a bug in auxgps ({type(err).__name__}: {err}); {where}; please report it", file=sys.stderr)
    return EXIT_BUG


if __name__ == "__main__":
    sys.exit(main())
