"""`auxgps replay`: the estimator run on a recorded flight, as fast as the machine allows, writing the flight's logs.

Without options it makes the calls the flight made, in the order it made them (the recording's journal), and so
reproduces the flight's decisions: the replayed ``gps_input.csv`` is the flight's. With ``deny_gps_after_s``,
GPS1 is hidden from the estimator from that many seconds after the recording's first message on, and the hidden
GPS1 reports score what auxgps would have sent instead (and the simulator's truth too, when the tlog holds it):
the check of auxgps on a flight of one's own, flown with a healthy GPS, before relying on it.

A damaged recording is replayed as far as it goes, with one line per problem (``ReplayResult.problems``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from auxgps.config import PipelineConfig, parse_as
from auxgps.core.estimator import Estimator, EstimatorOptions, FrameResult, Output
from auxgps.core.events import Frame, Gps1
from auxgps.core.geometry import LocalFrame
from auxgps.io.flight_log import FlightLog
from auxgps.io.link import Decoder, Truth
from auxgps.io.map_file import load_map
from auxgps.io.recording import open_recording


@dataclass
class ReplayResult:
    """What a replay did: counts, the outputs (for scoring), the hidden GPS1 reports and truth, and problems."""

    n_messages: int = 0
    n_frames: int = 0
    n_outputs: int = 0
    outputs: list[Output] = field(default_factory=list)
    hidden_gps1: list[Gps1] = field(default_factory=list)
    truth: list[Truth] = field(default_factory=list)
    frame: LocalFrame | None = None
    t_first_s: float | None = None
    deny_from_s: float | None = None
    clock_offset_s: float = 0.0
    problems: list[str] = field(default_factory=list)


def replay(folder: str | Path, out_dir: str | Path, *, deny_gps_after_s: float | None = None,
           pipeline: PipelineConfig | None = None) -> ReplayResult:
    """Replay the recording in ``folder``, writing the flight's logs to ``out_dir``."""
    rec = open_recording(folder)
    meta = rec.meta
    pipeline = pipeline or parse_as(PipelineConfig, meta["pipeline"], Path(folder) / "recording.json")
    o = meta.get("options", {})
    options = EstimatorOptions(gps_delay_s=float(o.get("gps_delay_s", 0.1)), gps1_lag_s=float(o.get("gps1_lag_s", 0.1)))
    landmarks = frame = None
    if meta.get("start_map"):
        landmarks, frame = load_map(Path(folder) / meta["start_map"])
    est = Estimator(pipeline, options, landmarks=landmarks, frame=frame)
    log = FlightLog(out_dir)
    decoder = Decoder()
    result = ReplayResult(clock_offset_s=rec.clock_offset_us / 1e6)
    messages = rec.messages()
    exhausted = False

    def feed_next() -> None:
        nonlocal exhausted
        try:
            msg, arrival_s = next(messages)
        except StopIteration:
            exhausted = True
            return
        result.n_messages += 1
        if result.t_first_s is None:
            result.t_first_s = arrival_s
            if deny_gps_after_s is not None:
                result.deny_from_s = arrival_s + deny_gps_after_s
        record = decoder(msg, arrival_s)
        if record is None:
            return
        if isinstance(record, Truth):
            result.truth.append(record)
            return
        if isinstance(record, Gps1) and result.deny_from_s is not None and record.t_s >= result.deny_from_s:
            result.hidden_gps1.append(record)
            return
        note = est.feed(record)
        if note:
            log.event(record.t_s, note)

    works: dict[int, object] = {}
    images = rec.images(entry.frame for entry in rec.journal if entry.call == "begin")
    try:
        for entry in rec.journal:
            while result.n_messages < entry.n_messages and not exhausted:
                feed_next()
            if entry.call == "begin":
                image = next(images)
                if image is None:
                    continue
                job = est.begin_frame(Frame(rec.frames[entry.frame][0], image))
                result.n_frames += 1
                if isinstance(job, FrameResult):
                    log.frame(job, est.frame)
                    if job.note:
                        log.event(job.t_s, job.note)
                else:
                    works[entry.frame] = est.process_frame(job)
            elif entry.call == "finish":
                work = works.pop(entry.frame, None)
                if work is not None:
                    res = est.finish_frame(work)
                    log.frame(res, est.frame)
                    if res.note:
                        log.event(res.t_s, res.note)
            else:
                out = est.output(entry.t_s, entry.t_unix_s)
                result.n_outputs += 1
                result.outputs.append(out)
                log.output(out)
                if out.decision.status:
                    log.event(out.t_s, out.decision.status)
        while not exhausted:
            feed_next()
        if exhausted and rec.journal and result.n_messages < rec.journal[-1].n_messages:
            rec.problems.append(f"flight.tlog: {result.n_messages} messages, where the journal counts "
                                f"{rec.journal[-1].n_messages}: the tlog is cut or damaged")
    finally:
        images.close()
        log.close()
    result.frame = est.frame
    result.problems = rec.problems
    return result


# -- scoring against the hidden GPS1 ---------------------------------------------------------------------------


def _track(times_s: np.ndarray, p_ne_m: np.ndarray, t_s: np.ndarray, max_gap_s: float) -> np.ndarray:
    """(N, 2) the reference track at ``t_s``, linear between its samples; NaN outside it or across a gap."""
    out = np.full((len(t_s), 2), np.nan)
    if len(times_s) < 2:
        return out
    k = np.searchsorted(times_s, t_s)
    inside = (k > 0) & (k < len(times_s))
    k = np.clip(k, 1, len(times_s) - 1)
    t0, t1 = times_s[k - 1], times_s[k]
    ok = inside & (t1 - t0 <= max_gap_s)
    w = np.where(ok, (t_s - t0) / np.where(t1 > t0, t1 - t0, 1.0), 0.0)[:, None]
    out[ok] = ((1 - w) * p_ne_m[k - 1] + w * p_ne_m[k])[ok]
    return out


def score(result: ReplayResult, lag_s: float) -> dict:
    """The outputs after GPS1 was hidden against the hidden GPS1 (and the truth, when recorded): horizontal error
    RMS, p95 and max over the 3D outputs, their share inside the reported 3 sigma, and availability (the share of
    outputs with a 3D fix). Each output is compared at the time it describes; the reference between its reports
    is linear, and GPS1 is taken at its measurement time (its report's time less the receiver's lag)."""
    if result.deny_from_s is None or result.frame is None:
        return {"scored": False, "reason": "no GPS1 hidden, or no local frame (no GPS1 fix before it was hidden)"}
    frame = result.frame
    outs = [o for o in result.outputs if o.gps is not None and o.t_described_s >= result.deny_from_s]
    if not outs:
        return {"scored": False, "reason": "no GPS_INPUT after GPS1 was hidden"}
    t = np.array([o.t_described_s for o in outs])
    fix3 = np.array([o.gps.fix_type == 3 for o in outs])
    p = frame.to_ned(lat_deg=np.array([o.gps.lat_deg for o in outs]), lon_deg=np.array([o.gps.lon_deg for o in outs]),
                     alt_amsl_m=np.array([o.gps.alt_amsl_m for o in outs]))[:, :2]
    sigma = np.array([o.gps.horiz_accuracy_m for o in outs])
    refs = {}
    good = [g for g in result.hidden_gps1 if g.fix_type >= 3]
    if good:
        refs["gps1"] = (np.array([g.t_s - lag_s for g in good]),
                        frame.to_ned(lat_deg=np.array([g.lat_deg for g in good]), lon_deg=np.array([g.lon_deg for g in good]),
                                     alt_amsl_m=np.array([g.alt_amsl_m for g in good]))[:, :2], 1.0)
    truth = [x for x in result.truth if x.t_s >= result.deny_from_s - 1.0]
    if truth:
        refs["truth"] = (np.array([x.t_s for x in truth]),
                         frame.to_ned(lat_deg=np.array([x.lat_deg for x in truth]), lon_deg=np.array([x.lon_deg for x in truth]),
                                      alt_amsl_m=np.full(len(truth), frame.alt_amsl_m))[:, :2], 0.5)
    figures = {"scored": bool(refs), "deny_after_s": result.deny_from_s - result.t_first_s, "outputs": len(outs)}
    series = {"t_s": t, "estimate_ne_m": p, "sigma_m": sigma, "fix3": fix3}
    for name, (t_ref, p_ref, gap) in refs.items():
        ref = _track(t_ref, p_ref, t, gap)
        covered = np.all(np.isfinite(ref), axis=1)
        use = covered & fix3
        err = np.linalg.norm(p - ref, axis=1)
        e = err[use]
        figures[name] = {
            "outputs_compared": int(covered.sum()),
            "availability": float(fix3[covered].mean()) if covered.any() else None,
            "rms_m": float(np.sqrt(np.mean(e**2))) if len(e) else None,
            "p95_m": float(np.percentile(e, 95)) if len(e) else None,
            "max_m": float(e.max()) if len(e) else None,
            "within_3sigma": float(np.mean(e <= 3 * sigma[use])) if len(e) else None,
            "seconds_compared": float(t[covered][-1] - t[covered][0]) if covered.sum() > 1 else 0.0,
        }
        series[f"{name}_ne_m"] = ref
        series[f"{name}_track"] = (t_ref, p_ref)
    figures["_series"] = series
    return figures


def score_lines(figures: dict) -> list[str]:
    """The scored figures as lines for the screen."""
    if not figures.get("scored"):
        return [f"not scored: {figures.get('reason', 'nothing to score against')}"]
    lines = [f"GPS1 hidden from {figures['deny_after_s']:.1f} s: {figures['outputs']} GPS_INPUT after it"]
    for name, label in (("gps1", "against the hidden GPS1"), ("truth", "against the simulator's truth")):
        f = figures.get(name)
        if not f or f["rms_m"] is None:
            continue
        lines.append(f"  {label} ({f['seconds_compared']:.0f} s, {f['outputs_compared']} outputs): horizontal error RMS {f['rms_m']:.3f} m, "
                     f"p95 {f['p95_m']:.3f} m, max {f['max_m']:.3f} m; inside the reported 3 sigma {f['within_3sigma']:.3f}; "
                     f"availability (3D fix) {f['availability']:.3f}")
    return lines


def write_trajectories(figures: dict, out_dir: str | Path, clock_offset_s: float, frame: LocalFrame) -> list[Path]:
    """The estimate and each reference as TUM trajectory files (UTC s, east north up m, identity attitude: evo
    reads them) and as one GeoJSON (QGIS shows it)."""
    out_dir = Path(out_dir)
    s = figures["_series"]
    written = []

    def tum(path: Path, t_s: np.ndarray, p_ne: np.ndarray) -> None:
        ok = np.all(np.isfinite(p_ne), axis=1)
        rows = np.column_stack([t_s[ok] + clock_offset_s, p_ne[ok, 1], p_ne[ok, 0], np.zeros((ok.sum(), 4)), np.ones(ok.sum())])
        np.savetxt(path, rows, fmt="%.6f", header="timestamp x_east_m y_north_m z_up_m qx qy qz qw")
        written.append(path)

    fix3 = s["fix3"]
    tum(out_dir / "estimate.tum", s["t_s"][fix3], s["estimate_ne_m"][fix3])
    features = []

    def line(name: str, p_ne: np.ndarray) -> None:
        ok = np.all(np.isfinite(p_ne), axis=1)
        if ok.sum() < 2:
            return
        lat, lon, _ = frame.to_geodetic(np.column_stack([p_ne[ok], np.zeros(ok.sum())]))
        features.append({"type": "Feature", "properties": {"name": name},
                         "geometry": {"type": "LineString", "coordinates": [[round(float(a), 8), round(float(b), 8)] for a, b in zip(lon, lat)]}})

    line("auxgps estimate (3D fix)", s["estimate_ne_m"][fix3])
    for name in ("gps1", "truth"):
        if f"{name}_track" in s:
            t_ref, p_ref = s[f"{name}_track"]
            tum(out_dir / f"reference_{name}.tum", t_ref, p_ref)
            line(f"reference: {name}", p_ref)
    geo = out_dir / "tracks.geojson"
    geo.write_text(json.dumps({"type": "FeatureCollection", "features": features}))
    written.append(geo)
    return written


def plot_report(figures: dict, path: str | Path) -> None:
    """A PNG: the track and the estimate, and the error over time with the reported 3 sigma."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = figures["_series"]
    t, p, sigma, fix3 = s["t_s"], s["estimate_ne_m"], s["sigma_m"], s["fix3"]
    fig, ax = plt.subplots(1, 2, figsize=(14, 5.5))
    for name, style in (("gps1", "-"), ("truth", ":")):
        if f"{name}_track" in s:
            _, p_ref = s[f"{name}_track"]
            ax[0].plot(p_ref[:, 1], p_ref[:, 0], style, label=f"reference: {name}")
            err = np.linalg.norm(p - s[f"{name}_ne_m"], axis=1)
            ax[1].plot(t - t[0], np.where(fix3, err, np.nan), ".", ms=2, label=f"error against {name}")
    ax[0].plot(p[fix3, 1], p[fix3, 0], ".", ms=2, label="auxgps (3D fix)")
    ax[0].set(xlabel="east (m)", ylabel="north (m)", title="track after GPS1 was hidden", aspect="equal")
    ax[0].legend(fontsize=8)
    ax[1].plot(t - t[0], np.where(fix3, 3 * sigma, np.nan), "k-", lw=0.8, label="reported 3 sigma")
    ax[1].set(xlabel="s after GPS1 was hidden", ylabel="m", title="horizontal error")
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def public(figures: dict) -> dict:
    """The figures without the series (for JSON)."""
    return {k: v for k, v in figures.items() if not k.startswith("_")}
