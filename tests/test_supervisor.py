"""The companion's decisions: when GPS1 is trusted, which mode, and what it announces."""

import numpy as np

from auxgps.core.supervisor import Gps1Sample, Mode, Supervisor, SupervisorConfig

P = np.array([1.0, 2.0, -15.0])
COV = np.eye(2) * 0.01


def good(t, p=P):
    return Gps1Sample(t, 6, 10, p, 0.05)


def test_healthy_gps1_means_mapping():
    s = Supervisor()
    s.gps1(good(0.0), None, None)
    d = s.decide(0.1, sigma_h_worst_m=0.05, last_correction_t_s=0.0)
    assert d.mode == Mode.MAPPING and d.gps1_trusted and d.status == "auxgps: mapping"


def test_lost_gps1_switches_to_positioning_at_once_and_says_so():
    s = Supervisor()
    s.gps1(good(0.0), None, None)
    s.decide(0.1, sigma_h_worst_m=0.05, last_correction_t_s=0.0)
    s.gps1(Gps1Sample(1.5, 0, 3, P, 99.0), P, COV)
    d = s.decide(1.6, sigma_h_worst_m=0.1, last_correction_t_s=1.5)
    assert d.mode == Mode.POSITIONING and not d.gps1_trusted
    assert "GPS1 lost" in d.status and "positioning" in d.status


def test_jump_is_distrusted_and_named():
    s = Supervisor()
    s.gps1(good(0.0), None, None)
    s.gps1(good(1.0, P + [30.0, 0.0, 0.0]), P, COV)  # spoofed: 30 m off our estimate
    assert not s.gps1_trusted and "disagrees" in s.disagreement


def test_small_offsets_are_not_jumps():
    s = Supervisor()
    s.gps1(good(0.0), None, None)
    s.gps1(good(1.0, P + [0.5, 0.0, 0.0]), P, np.eye(2) * 1e-4)  # 0.5 m: latency or noise, not a spoofer
    assert s.gps1_trusted and s.disagreement is None


def test_gps1_rejoins_only_after_agreeing_for_rejoin_s():
    cfg = SupervisorConfig(rejoin_s=10.0)
    s = Supervisor(cfg)
    s.gps1(good(0.0), None, None)
    s.gps1(Gps1Sample(1.0, 0, 3, P, 99.0), P, COV)
    assert not s.gps1_trusted
    for t in np.arange(2.0, 11.9, 0.2):
        s.gps1(good(t), P, COV)
        assert not s.gps1_trusted
    s.gps1(good(12.0), P, COV)
    assert s.gps1_trusted


def test_no_recent_correction_means_no_fix():
    s = Supervisor()
    assert s.decide(0.0, sigma_h_worst_m=None, last_correction_t_s=None).mode == Mode.NO_FIX
    assert s.decide(20.0, sigma_h_worst_m=0.1, last_correction_t_s=2.0).mode == Mode.NO_FIX  # 18 s old
    assert s.decide(20.0, sigma_h_worst_m=0.5, last_correction_t_s=8.0).mode == Mode.POSITIONING  # 12 s on the IMU
    assert s.decide(10.0, sigma_h_worst_m=5.0, last_correction_t_s=9.9).mode == Mode.NO_FIX  # too uncertain


def test_status_lines_at_most_one_a_second():
    s = Supervisor()
    s.gps1(good(0.0), None, None)
    first = s.decide(0.0, sigma_h_worst_m=0.05, last_correction_t_s=0.0)
    s.gps1(Gps1Sample(0.2, 0, 3, P, 99.0), P, COV)
    second = s.decide(0.3, sigma_h_worst_m=0.1, last_correction_t_s=0.2)
    third = s.decide(1.0, sigma_h_worst_m=0.1, last_correction_t_s=0.9)
    assert first.status is not None and second.status is None and third.status is not None
    assert "positioning" in third.status


def test_gps1_rejoins_at_once_when_auxgps_has_no_position_of_its_own():
    """After a link outage (no IMU for seconds) auxgps's estimate is metres loose: nothing to check GPS1 against."""
    s = Supervisor(SupervisorConfig(rejoin_s=10.0, max_sigma_h_m=2.0))
    s.gps1(good(0.0), None, None)
    s.gps1(Gps1Sample(1.0, 0, 3, P, 99.0), P, COV)
    assert not s.gps1_trusted
    s.gps1(good(1.2), P, np.eye(2) * 1.9**2)  # still a position of its own: wait
    assert not s.gps1_trusted
    s.gps1(good(1.4), P, np.diag([0.5, 2.5**2]))  # 2.5 m along its worst axis: trust GPS1 now
    assert s.gps1_trusted
    said = [s.decide(t, sigma_h_worst_m=2.5, last_correction_t_s=1.4).status for t in (1.5, 2.5, 3.5)]
    assert any("no position of its own" in (line or "") for line in said), said


def test_a_gps1_dragged_away_from_the_map_is_distrusted_and_rejoins_only_on_a_tight_agreement():
    """Self-checks (fix on the map minus the filter, which follows GPS1) of 0.1 m noise, then a drag of 0.5 m/s:
    found as the mean of 3 passes 0.5 m; then GPS1 within 2 m of a loose estimate does not rejoin, and rejoins
    only after agreeing for rejoin_s with an estimate tighter than drag_m."""
    rng = np.random.default_rng(1)
    s = Supervisor()
    s.gps1(good(0.0), None, None)
    cov = np.eye(2) * 0.1**2
    found = None
    for k in range(200):
        t = 0.5 * k
        drag = max(0.0, t - 60.0) * 0.5
        line = s.visual_check(t, np.array([drag, 0.0]) * -1 + rng.normal(0, 0.1, 2), cov)
        if line:
            found = t
            break
    assert found is not None and 60.0 < found <= 62.5 and not s.gps1_trusted and "GPS1 drifts" in line
    # Lost meanwhile (own sigma 1 m): GPS1 0.8 m off agrees within 2 m and within 3.7 sigma, but must not rejoin
    for k in range(30):
        s.gps1(good(70.0 + k, P + np.array([0.8, 0.0, 0.0])), P, np.eye(2) * 1.0)
    assert not s.gps1_trusted
    # Tight again (0.1 m) and GPS1 right on it for rejoin_s: trusted
    for k in range(12):
        s.gps1(good(100.0 + k), P, COV)
    assert s.gps1_trusted


def test_an_inflated_accuracy_is_distrusted_absolutely_and_against_its_own_usual():
    s = Supervisor(SupervisorConfig(max_gps1_h_acc_m=3.0, h_acc_inflation=4.0))
    for k in range(20):
        s.gps1(Gps1Sample(0.2 * k, 6, 10, P, 0.3), P if k else None, COV if k else None)
    assert s.gps1_trusted
    s.gps1(Gps1Sample(4.2, 6, 10, P, 1.5), P, COV)  # 1.5 m: under 3 m, but over 4 x its usual 0.3 m
    assert not s.gps1_trusted
    line = [s.decide(4.2 + t, sigma_h_worst_m=0.1, last_correction_t_s=4.2 + t) for t in (0.0, 1.0)][0].status
    assert line.startswith("GPS1 accuracy 1.5 m: distrusted") and "usually 0.30 m" in line
    fresh = Supervisor(SupervisorConfig(max_gps1_h_acc_m=3.0))
    fresh.gps1(Gps1Sample(0.0, 6, 10, P, 5.0), None, None)  # a first report over the absolute limit
    assert not fresh.gps1_trusted


def test_a_run_of_gps1_reports_the_filter_rejects_distrusts_gps1_strictly():
    s = Supervisor()
    s.gps1(good(0.0), None, None)
    line = s.gps1_rejected(31.1, 1.1)
    assert not s.gps1_trusted and line.startswith("GPS1 off track 1.1 m: distrusted, no mapping")
    assert s.gps1_rejected(31.3, 1.3) is None  # said once
    for k in range(30):  # 0.8 m off a loose estimate: within 2 m, but the rejoin is strict after such a run
        s.gps1(good(32.0 + k, P + np.array([0.8, 0.0, 0.0])), P, np.eye(2) * 1.0)
    assert not s.gps1_trusted


def test_gps1_found_off_track_takes_what_the_filter_followed_from_the_latest_self_checks():
    """The filter follows a drag partway before its gate rejects GPS1; the map's self-checks just before say how
    far (the estimator loosens the filter by that, as when the self-checks find the drag themselves). Self-checks
    older than drag_window_s say nothing of now."""
    cov = np.eye(2) * 0.05**2
    s = Supervisor()
    s.gps1(good(0.0), None, None)
    for k, d in enumerate([0.30, 0.35, 0.40]):  # within drag_m: not a drag by themselves
        assert s.visual_check(30.0 + 0.1 * k, np.array([-d, -d]) / np.sqrt(2), cov) is None
    assert s.drag_seen_ne_m is None
    s.gps1_rejected(30.5, 0.6)
    np.testing.assert_allclose(s.drag_seen_ne_m, -np.array([0.35, 0.35]) / np.sqrt(2))
    old = Supervisor()
    old.gps1(good(0.0), None, None)
    for k in range(3):
        old.visual_check(10.0 + 0.1 * k, np.array([0.4, 0.0]), cov)
    old.gps1_rejected(10.2 + old.cfg.drag_window_s + 0.1, 0.6)
    assert old.drag_seen_ne_m is None


def test_status_lines_come_one_at_a_time_in_order_each_whole():
    s = Supervisor(SupervisorConfig(status_interval_s=1.0))
    s.gps1(good(0.0), None, None)
    s.gps1_rejected(0.1, 2.0)
    said = [s.decide(t, sigma_h_worst_m=0.1, last_correction_t_s=t).status for t in (0.2, 0.5, 1.2, 2.2, 3.2)]
    assert said[0].startswith("GPS1 off track 2.0 m") and said[1] is None and said[2] == "auxgps: positioning"
    assert all(len(line) < 121 for line in said if line)


def test_a_gps1_that_keeps_dropping_out_does_not_rejoin():
    s = Supervisor(SupervisorConfig(rejoin_s=10.0, stale_s=1.0))
    s.gps1(good(0.0), None, None)
    s.gps1(Gps1Sample(0.2, 0, 3, P, 99.0), P, COV)
    for t in np.arange(0.4, 30.0, 0.2):
        if (t % 5.0) < 1.5:  # silent for 1.5 s of every 5 s
            continue
        s.gps1(good(t), P, COV)
        assert not s.gps1_trusted, t


def test_landmarks_since_the_last_agreeing_self_check_are_unverified():
    s = Supervisor(SupervisorConfig(self_check_age_s=10.0))
    s.gps1(good(0.0), None, None)
    assert s.unverified_since_s() == -np.inf  # no self-check has agreed: the whole flight's map is unverified
    cov = np.eye(2) * 0.05**2
    for t in (20.0, 20.5, 21.0):
        s.visual_check(t, np.array([0.05, 0.0]), cov)
    assert s.unverified_since_s() == 11.0  # the last agreeing run (21 s) vouched for what was 10 s old then
    for t in (40.0, 40.5, 41.0):  # 0.8 m off: found dragged; the agreement time stays
        line = s.visual_check(t, np.array([0.8, 0.0]), cov)
    assert line and s.unverified_since_s() == 11.0
