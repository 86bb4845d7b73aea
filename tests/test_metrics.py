"""Evaluation figures on hand-made run records: known answers."""

import numpy as np
import pytest

from auxgps.cli import summary_table
from auxgps.evaluation.metrics import summarize
from auxgps.evaluation.scenario import RunRecord


def record(fused_t_s, fused_err_ne_m, fused_sigma_m, fix_applied_t_s, fix_gated, denied_from_s=10.0, seed=1,
           fused_vel_err_ne_m_s=None):
    n_fix = len(fix_applied_t_s)
    if fused_vel_err_ne_m_s is None:
        fused_vel_err_ne_m_s = np.zeros((len(fused_t_s), 2))
    return RunRecord(
        seed=seed,
        landmark_err_ne_m=np.zeros((1, 2)),
        landmark_seen_err_ne_m=np.zeros((1, 2)),
        fix_err_ne_m=np.full((n_fix, 2), 0.1),
        fix_sigma_h_rms_m=np.full(n_fix, 0.1),
        fix_gated=np.array(fix_gated, bool),
        n_eligible_frames=n_fix,
        n_eligible_fixed=n_fix,
        n_positioning_frames=n_fix,
        fused_t_s=np.asarray(fused_t_s, float),
        fused_err_ne_m=np.asarray(fused_err_ne_m, float),
        fused_cov_ne_m2=np.array([np.eye(2) * s**2 for s in fused_sigma_m]),
        fused_vel_err_ne_m_s=np.asarray(fused_vel_err_ne_m_s, float),
        fix_applied_t_s=np.asarray(fix_applied_t_s, float),
        denied_from_s=denied_from_s,
        denied_s=10.0,
        mapping_ms=np.ones(1),
        positioning_ms=np.ones(n_fix),
        features_per_frame=np.full(n_fix, 100),
    )


def test_fused_consistency_known_answers():
    """Errors (0.3, 0.4) and (0, 0.1) against a 0.1 m sigma: NEES 25 and 1, and only the second inside 3 sigma."""
    r = record([10.0, 10.1], [[0.3, 0.4], [0.0, 0.1]], [0.1, 0.1], [10.0], [False])
    fused = summarize([r])["fused"]
    assert fused["nees_mean"] == pytest.approx(13.0)
    assert fused["within_3sigma"] == pytest.approx(0.5)
    assert fused["max_m"] == pytest.approx(0.5)
    assert fused["rms_m"] == pytest.approx(np.sqrt((0.25 + 0.01) / 2))


def test_gap_figures_count_accepted_fixes_only():
    """GPS lost at 10 s; fixes given to the filter at 11 s (accepted), 13 s (gated out) and 16 s (accepted), and
    one captured too late to reach it (NaN); outputs every second to 18 s, the worst error at 15 s. The gated fix
    does not end the gap: the longest is 11 -> 16 s, and the maximum came 4 s after the last accepted fix."""
    t = np.arange(10.0, 18.5, 1.0)
    err = np.zeros((len(t), 2))
    err[t == 15.0] = [0.0, 0.6]
    r = record(t, err, np.full(len(t), 0.1), [11.0, 13.0, 16.0, np.nan], [False, True, False, False])
    fused = summarize([r])["fused"]
    assert fused["longest_gap_s"] == pytest.approx(4.0)  # measured at the outputs: 15 s is the last before 16 s
    assert fused["since_fix_at_max_s"] == pytest.approx(4.0)


def test_velocity_error_where_a_long_stretch_without_fixes_begins():
    """GPS lost at 10 s; fixes accepted on arrival at 11 s, 16 s and 16.5 s; outputs every half second to 18 s.
    Stretches: 10 -> 11 s (1 s), 11 -> 16 s (5 s), 16 -> 16.5 s and 16.5 -> 18 s (1.5 s): one of 2 s or more, and
    its velocity error is the output's at 11 s, where it began, (0.3, 0.4) m/s: 0.5 m/s."""
    t = np.arange(10.0, 18.01, 0.5)
    v_err = np.full((len(t), 2), 0.01)
    v_err[t == 11.0] = [0.3, 0.4]
    v_err[t == 13.0] = [3.0, 4.0]  # inside the stretch, not where it began
    r = record(t, np.zeros((len(t), 2)), np.full(len(t), 0.1), [11.0, 16.0, 16.5], [False] * 3, fused_vel_err_ne_m_s=v_err)
    long_gaps = summarize([r])["fused"]["long_gaps"]
    assert long_gaps["count"] == 1
    assert long_gaps["velocity_error_max_m_s"] == pytest.approx(0.5)
    assert long_gaps["velocity_error_rms_m_s"] == pytest.approx(0.5)


def test_gap_from_the_loss_of_gps_when_no_fix_is_accepted():
    t = np.arange(10.0, 13.5, 0.5)
    r = record(t, np.zeros((len(t), 2)), np.full(len(t), 0.1), [11.0], [True])
    assert summarize([r])["fused"]["longest_gap_s"] == pytest.approx(3.0)


def test_only_fixes_the_filter_kept_count_as_accepted():
    """Three fixes 0.6 m off: one kept, one gated out, one that never reached the filter (NaN arrival)."""
    r = record([10.0, 10.1], np.zeros((2, 2)), [0.1, 0.1], [10.0, 10.05, np.nan], [False, True, False])
    r.fix_err_ne_m[:] = [0.0, 0.6]
    r.fix_err_ne_m[1] = [0.0, 0.9]  # the gated one: not the largest accepted
    gate = summarize([r])["gate"]
    assert gate["accepted_over_0_5m"] == 1 and gate["rejected"] == 1
    assert gate["accepted_max_m"] == pytest.approx(0.6)


def test_a_run_without_positioning_frames_is_summarised_and_printed():
    """A flight whose denied part produced no frame (no features, no fixes): its figures are absent, not NaN,
    and the on-screen table prints them as '-'."""
    r = record([10.0, 10.1], np.zeros((2, 2)), [0.1, 0.1], [], [])
    summary = summarize([r])
    assert summary["features_per_frame_median"] is None
    summary["scenario"] = {"world": "w.yaml", "altitude_m": 15.0, "runs": 1, "fps": 2.0, "seeds": [1]}
    assert "(features per frame: -)" in summary_table(summary)


def test_a_featureless_crossing_is_scored_from_what_gps_input_said():
    """Denied from 10 s, outputs every second to 30 s; over a featureless patch from 12 to 20 s. GPS_INPUT keeps a
    3D fix to 15 s then says no fix to 24 s; the true error outgrows three times the reported accuracy at 20 s only.
    One fix is accepted over the patch (captured at 12 s, 0.3 m off)."""
    t = np.arange(10.0, 31.0, 1.0)
    err = np.zeros((len(t), 2))
    err[:, 0] = np.where(t == 20.0, 1.0, 0.1)
    r = record(t, err, np.full(len(t), 0.3), [12.0, 24.0], [False, False])
    r.fix_err_ne_m[0] = [0.3, 0.0]
    r.fix_over_patch = np.array([True, False])
    r.fused_over_patch = (t >= 12.0) & (t <= 20.0)
    r.fused_height_agl_m = np.full(len(t), 40.0)
    r.gps_fix_type = np.where((t > 15.0) & (t < 24.0), 1, 3)
    r.gps_h_acc_m = np.full(len(t), 0.3)
    summary = summarize([r])
    f = summary["featureless"]
    assert f["crossings"] == 1 and f["seconds_over"] == pytest.approx(8.0)
    assert f["accepted_fixes"] == 1 and f["accepted_fix_max_m"] == pytest.approx(0.3)
    assert f["within_3_reported"] == pytest.approx(8 / 9)
    assert f["said_no_fix"] == 1 and f["no_fix_after_s"] == pytest.approx(4.0)
    assert f["fix_3d_again_s"] == pytest.approx(4.0)
    g = summary["gps_input"]
    assert g["outputs"] == 21 and g["fix_3d_share"] == pytest.approx(13 / 21) and g["within_3_reported"] == 1.0
    assert summary["height_agl"] == {"min_m": 40.0, "median_m": 40.0, "max_m": 40.0}
    summary["scenario"] = {"world": "w.yaml", "altitude_m": None, "runs": 1, "fps": 2.0, "seeds": [1]}
    table = summary_table(summary)
    assert "at the mission heights" in table and "featureless ground: 1 crossing(s), 8 s over it" in table


def test_a_world_without_patches_has_no_featureless_figures():
    r = record([10.0, 10.1], np.zeros((2, 2)), [0.1, 0.1], [10.0], [False])
    assert summarize([r])["featureless"] is None
