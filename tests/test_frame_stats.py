"""What `auxgps run` says the frame loop kept up with: frames processed and dropped, capture to GPS_INPUT."""

import numpy as np

from auxgps.companion import FrameStats


def test_frame_figures_time_each_frame_from_its_capture_to_the_first_gps_input_after_it_was_done():
    stats = FrameStats()
    stats.frame_done(0.50, 15.0)  # before any GPS_INPUT (no GPS1 fix yet): processed, no latency
    stats.gps_input_sent(0.95)
    stats.frame_done(1.00, 20.0)
    stats.frame_done(1.03, 30.0)
    stats.gps_input_sent(1.10)  # carries both
    stats.gps_input_sent(1.20)  # carries none
    stats.frame_done(1.15, 25.0)
    stats.gps_input_sent(1.30)
    fig = stats.figures(delivered=10, dropped=7)
    assert np.allclose(sorted(stats.latency_ms), [70.0, 100.0, 150.0])
    assert fig["frames_processed"] == 4 and fig["frames_delivered"] == 10 and fig["frames_dropped"] == 7
    assert fig["capture_to_gps_input_ms"]["median"] == 100.0 and fig["processing_ms"]["max"] == 30.0
