"""Figures of merit from :class:`RunRecord` s: per run and pooled over runs (RMS over all frames, max over all)."""

from __future__ import annotations

import numpy as np

from auxgps.evaluation.scenario import RunRecord


def _stats(err_m: np.ndarray) -> dict:
    if len(err_m) == 0:
        return {"count": 0, "rms_m": None, "median_m": None, "p95_m": None, "max_m": None}
    return {
        "count": int(len(err_m)),
        "rms_m": float(np.sqrt(np.mean(err_m**2))),
        "median_m": float(np.median(err_m)),
        "p95_m": float(np.percentile(err_m, 95)),
        "max_m": float(np.max(err_m)),
    }


def _mean_abs_ne(err_ne: np.ndarray) -> float | None:
    """The thesis' figure: hypot(mean |north error|, mean |east error|)."""
    if len(err_ne) == 0:
        return None
    return float(np.hypot(*np.mean(np.abs(err_ne), axis=0)))


def _since_accepted_fix_s(r: RunRecord) -> np.ndarray:
    """(O,) seconds from the last accepted fix's arrival at the filter (or from the loss of GPS) to each fused
    output: how long the output had been carried on the IMU alone."""
    t_ref = np.concatenate([[r.denied_from_s], np.sort(r.fix_applied_t_s[r.fix_accepted])])
    k = np.searchsorted(t_ref, r.fused_t_s, side="right") - 1  # outputs are all while denied: k >= 0
    return r.fused_t_s - t_ref[k]


#: A stretch without an accepted fix at least this long is one whose drift the velocity at its start decides, s.
LONG_GAP_S = 2.0


def _velocity_error_at_long_gaps(r: RunRecord, since: np.ndarray) -> np.ndarray:
    """(G,) horizontal velocity error (m/s) of the output at the start of each stretch of at least
    :data:`LONG_GAP_S` without an accepted fix: the first output after the fix that began it (or after the loss of
    GPS). Carried on the IMU alone, the output drifts by about this times the stretch. ``since``: the run's
    :func:`_since_accepted_fix_s`."""
    if len(since) == 0 or len(r.fused_vel_err_ne_m_s) != len(since):
        return np.zeros(0)
    starts = np.flatnonzero(np.r_[True, np.diff(since) < 0])  # the count restarts: a fix arrived
    ends = np.r_[starts[1:], len(since)] - 1  # the last output before the next restart
    long = since[ends] >= LONG_GAP_S
    return np.linalg.norm(r.fused_vel_err_ne_m_s[starts[long]], axis=1)


def _fused(records: list[RunRecord]) -> dict:
    """The filter's output while denied: horizontal error, and its consistency with the reported covariance.

    And what explains a maximum: the longest stretch without an accepted fix (dead reckoning on the IMU alone),
    and how long the output at the maximum had gone without one; and the velocity error the output had when such a
    stretch began."""
    err = np.vstack([r.fused_err_ne_m for r in records])
    cov = np.concatenate([r.fused_cov_ne_m2 for r in records])
    if len(err) == 0:
        return {"count": 0, "rms_m": None, "p95_m": None, "max_m": None, "nees_mean": None, "within_3sigma": None,
                "longest_gap_s": None, "since_fix_at_max_s": None,
                "long_gaps": {"min_s": LONG_GAP_S, "count": 0, "velocity_error_rms_m_s": None, "velocity_error_max_m_s": None}}
    e = np.linalg.norm(err, axis=1)
    nees = np.einsum("ni,nij,nj->n", err, np.linalg.inv(cov), err)  # 2 degrees of freedom: 2 expected
    sigma_worst = np.sqrt(np.linalg.eigvalsh(cov)[:, -1])  # the horizontal accuracy auxgps reports
    since_per_run = [_since_accepted_fix_s(r) for r in records]
    since = np.concatenate(since_per_run)
    v_gap = np.concatenate([_velocity_error_at_long_gaps(r, s) for r, s in zip(records, since_per_run)])
    return {
        "count": int(len(e)),
        "rms_m": float(np.sqrt(np.mean(e**2))),
        "p95_m": float(np.percentile(e, 95)),
        "max_m": float(e.max()),
        "nees_mean": float(np.mean(nees)),
        "within_3sigma": float(np.mean(e <= 3.0 * sigma_worst)),
        "longest_gap_s": float(since.max()),
        "since_fix_at_max_s": float(since[np.argmax(e)]),
        "long_gaps": {
            "min_s": LONG_GAP_S,
            "count": int(len(v_gap)),
            "velocity_error_rms_m_s": float(np.sqrt(np.mean(v_gap**2))) if len(v_gap) else None,
            "velocity_error_max_m_s": float(v_gap.max()) if len(v_gap) else None,
        },
    }


def _blackout(records: list[RunRecord]) -> dict | None:
    """Per run: outputs during the blackout, reported accuracy before and at its end, true error at its end,
    and how long after it the error is back under 0.3 m and the reported accuracy back under twice its level
    before (the worst run is pooled)."""
    runs = [r for r in records if r.blackout_s is not None and len(r.fused_t_s)]
    if not runs:
        return None
    out = []
    for r in runs:
        t0, t1 = r.blackout_s
        t = r.fused_t_s
        e = np.linalg.norm(r.fused_err_ne_m, axis=1)
        sig = np.sqrt(np.linalg.eigvalsh(r.fused_cov_ne_m2)[:, -1])
        before = int(np.searchsorted(t, t0) - 1)
        end = int(np.searchsorted(t, t1) - 1)
        inside = (t >= t0) & (t < t1)
        ok = (e <= 0.3) & (sig <= 2.0 * sig[before]) & (t >= t1)
        rec = np.flatnonzero(ok)
        out.append(
            {
                "outputs_during": int(inside.sum()),
                "sigma_before_m": float(sig[before]),
                "sigma_at_end_m": float(sig[end]),
                "error_at_end_m": float(e[end]),
                "recovery_s": float(t[rec[0]] - t1) if len(rec) else None,
            }
        )
    worst = {
        "outputs_during": min(o["outputs_during"] for o in out),
        "sigma_before_m": max(o["sigma_before_m"] for o in out),
        "sigma_at_end_m": min(o["sigma_at_end_m"] for o in out),
        "error_at_end_m": max(o["error_at_end_m"] for o in out),
        "recovery_s": None if any(o["recovery_s"] is None for o in out) else max(o["recovery_s"] for o in out),
    }
    return worst


def _heights(records: list[RunRecord]) -> dict | None:
    """The true height above ground while denied, m: the one the figures are a share of."""
    h = np.concatenate([r.fused_height_agl_m for r in records])
    if not len(h):
        return None
    return {"min_m": float(h.min()), "median_m": float(np.median(h)), "max_m": float(h.max())}


def _gps_input(records: list[RunRecord]) -> dict:
    """What GPS_INPUT said while denied: the share of outputs with a 3D fix, and of those, the share whose true
    error is inside three times the horizontal accuracy they reported."""
    e = np.concatenate([np.linalg.norm(r.fused_err_ne_m, axis=1) for r in records])
    fix_3d = np.concatenate([r.gps_fix_type for r in records]) == 3
    h_acc = np.concatenate([r.gps_h_acc_m for r in records])
    if not len(e) or len(h_acc) != len(e):
        return {"outputs": 0, "fix_3d_share": None, "within_3_reported": None}
    return {"outputs": int(len(e)), "fix_3d_share": float(fix_3d.mean()),
            "within_3_reported": float(np.mean(e[fix_3d] <= 3.0 * h_acc[fix_3d])) if fix_3d.any() else None}


def _crossings(over: np.ndarray) -> list[tuple[int, int]]:
    """(start, end) output indices, end exclusive, of each run of outputs over a featureless patch."""
    edges = np.flatnonzero(np.diff(np.r_[0, over.astype(int), 0]))
    return list(zip(edges[::2], edges[1::2]))


def _featureless(records: list[RunRecord]) -> dict | None:
    """Crossings of the world's featureless patches while denied (None: none). Pooled over crossings: the time
    over them, the accepted fixes captured over them and their largest error, the share of outputs over them whose
    true error is inside three times GPS_INPUT's reported accuracy; how many crossings made GPS_INPUT say "no
    fix", the longest it took after entering, and the longest from leaving to a 3D fix again (negative: before the
    vehicle left, the camera seeing the shore; None: not before the flight ended)."""
    rows = []
    for r in records:
        if not len(r.fused_over_patch) or not r.fused_over_patch.any():
            continue
        t, e, fix_3d = r.fused_t_s, np.linalg.norm(r.fused_err_ne_m, axis=1), r.gps_fix_type == 3
        for a, b in _crossings(r.fused_over_patch):
            lost = a + np.flatnonzero(~fix_3d[a:b])
            again = lost[0] + np.flatnonzero(fix_3d[lost[0]:]) if len(lost) else []
            rows.append({
                "s": float(t[b - 1] - t[a]),
                "honest": e[a:b] <= 3.0 * r.gps_h_acc_m[a:b],
                "no_fix_after_s": float(t[lost[0]] - t[a]) if len(lost) else None,
                "fix_3d_again_s": float(t[again[0]] - t[b - 1]) if len(again) else None,
            })
    if not rows:
        return None
    scored = [r for r in records if len(r.fix_over_patch) == len(r.fix_err_ne_m)]
    over_fix = np.concatenate([np.zeros(0, bool)] + [r.fix_over_patch & r.fix_accepted for r in scored])
    fix_e = np.concatenate([np.zeros(0)] + [np.linalg.norm(r.fix_err_ne_m, axis=1) for r in scored])
    said = [row for row in rows if row["no_fix_after_s"] is not None]
    again = [row["fix_3d_again_s"] for row in said]
    return {
        "crossings": len(rows),
        "seconds_over": float(sum(row["s"] for row in rows)),
        "accepted_fixes": int(over_fix.sum()),
        "accepted_fix_max_m": float(fix_e[over_fix].max()) if over_fix.any() else None,
        "within_3_reported": float(np.mean(np.concatenate([row["honest"] for row in rows]))),
        "said_no_fix": len(said),
        "no_fix_after_s": max((row["no_fix_after_s"] for row in said), default=None),
        "fix_3d_again_s": None if None in again or not again else max(again),
    }


def summarize(records: list[RunRecord]) -> dict:
    """Pooled figures over ``records``, with each run's own under ``runs``."""
    pooled = _summarize_pooled(records)
    if len(records) > 1:
        pooled["runs"] = [dict(_summarize_pooled([r]), seed=r.seed) for r in records]
    else:
        pooled["runs"] = [dict(_summarize_pooled(records), seed=records[0].seed)]
    return pooled


def _summarize_pooled(records: list[RunRecord]) -> dict:
    lm_ne = np.vstack([r.landmark_err_ne_m for r in records])
    fix_ne = np.vstack([r.fix_err_ne_m for r in records])
    lm = _stats(np.linalg.norm(lm_ne, axis=1))
    lm_seen = _stats(np.linalg.norm(np.vstack([r.landmark_seen_err_ne_m for r in records]), axis=1))
    fx = _stats(np.linalg.norm(fix_ne, axis=1))
    n_elig = sum(r.n_eligible_frames for r in records)
    fx["availability"] = (sum(r.n_eligible_fixed for r in records) / n_elig) if n_elig else None
    fx["over_0_5m"] = int(np.sum(np.linalg.norm(fix_ne, axis=1) > 0.5))
    fx["eligible_frames"] = int(n_elig)
    fx["positioning_frames"] = int(sum(r.n_positioning_frames for r in records))
    fx["followed"] = int(sum(int(np.sum(r.fix_followed)) for r in records))  # of them from optical flow, not a detection
    all_ms = np.concatenate([np.concatenate([r.mapping_ms, r.positioning_ms]) for r in records])
    n_feat = np.concatenate([r.features_per_frame for r in records])
    pos_ms = np.concatenate([r.positioning_ms for r in records])
    map_ms = np.concatenate([r.mapping_ms for r in records])
    fused = _fused(records)
    gated = np.concatenate([r.fix_gated for r in records])
    accepted = np.concatenate([r.fix_accepted for r in records])
    reasons: dict[str, int] = {}
    for r in records:
        for k, v in r.no_fix_reasons.items():
            reasons[k] = reasons.get(k, 0) + v
    return {
        "landmarks": {k: lm[k] for k in ("count", "rms_m", "median_m", "max_m")},
        "landmarks_seen_over_10": {k: lm_seen[k] for k in ("count", "rms_m", "median_m", "max_m")},
        "fixes": fx,
        "mission_average": {
            "landmark_m": _mean_abs_ne(lm_ne),
            # The thesis compared the mission's average fix with the average true position.
            "position_m": float(np.linalg.norm(np.mean(fix_ne, axis=0))) if len(fix_ne) else None,
        },
        "fused": fused,
        "gate": {
            "rejected": int(gated.sum()),
            "accepted_over_0_5m": int(np.sum(accepted & (np.linalg.norm(fix_ne, axis=1) > 0.5))),
            "accepted_max_m": float(np.linalg.norm(fix_ne[accepted], axis=1).max()) if accepted.any() else None,
            "reinitialisations": int(sum(r.n_reinit for r in records)),
        },
        "denied_s": float(np.mean([r.denied_s for r in records])),
        "height_agl": _heights(records),
        "gps_input": _gps_input(records),
        "featureless": _featureless(records),
        "blackout": _blackout(records),
        "per_frame_ms": {
            "median": float(np.median(all_ms)) if len(all_ms) else None,
            "p99": float(np.percentile(all_ms, 99)) if len(all_ms) else None,
            "mapping_median": float(np.median(map_ms)) if len(map_ms) else None,
            "positioning_median": float(np.median(pos_ms)) if len(pos_ms) else None,
        },
        "features_per_frame_median": float(np.median(n_feat)) if len(n_feat) else None,
        "no_fix_reasons": reasons,
        # What the estimator said for the events log in the positioning flight (the first run's, with times).
        "notes": [[round(t, 2), line] for t, line in (records[0].notes if records else [])],
    }
