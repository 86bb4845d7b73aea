#!/usr/bin/env python3
"""How far the mapper's triangulation puts a landmark from the truth on average, for a few views close together.

    .venv/bin/python tools/triangulation_bias.py [--sigma-mrad 3.8] [--trials 4000] [--corrected]

A camera 40 m up flies past a ground point 10 m to its side; each view's ray direction has white noise of
``--sigma-mrad`` per axis (the emulator's 0.2 deg of tilt and a pixel, 3.8 mrad). The point is solved as the
mapper solves it (``auxgps.core.mapping.ray_information``: the projector across each ray over the ray's
sigma squared, summed, with a new landmark's ground-plane prior, ``mapping.initial_height_sigma_m``), and the mean error printed for
baselines of 9 to 44 m. The closest point to noisy rays lies toward the cameras: the smaller the parallax, the
more (docs/missions.md). ``--corrected`` takes ``2 s^2 d d^T`` off each ray's projector, which removes the
bias's expectation to first order.
"""
import argparse

import numpy as np

from auxgps.config import MappingConfig
from auxgps.core.mapping import ray_information


def mean_error(n_views: int, baseline_m: float, sigma_rad: float, corrected: bool, trials: int, rng) -> tuple[np.ndarray, float]:
    """Mean (north, east, down) error of the solved point, m, and the standard deviation of its down error."""
    point = np.array([0.0, 10.0, 0.0])
    cams = np.column_stack([np.linspace(-baseline_m / 2, baseline_m / 2, n_views), np.zeros(n_views), np.full(n_views, -40.0)])
    true_d = point - cams
    range_m = np.linalg.norm(true_d, axis=1)
    true_d /= range_m[:, None]
    errors = np.empty((trials, 3))
    for k in range(trials):
        e = rng.standard_normal((n_views, 3)) * sigma_rad
        e -= np.einsum("ki,ki->k", e, true_d)[:, None] * true_d
        d = true_d + e
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        A = ray_information(d, range_m * sigma_rad)
        if corrected:
            A -= (2.0 * sigma_rad**2 / (range_m * sigma_rad) ** 2)[:, None, None] * d[:, :, None] * d[:, None, :]
        info = A.sum(axis=0)
        info[2, 2] += 1.0 / MappingConfig().initial_height_sigma_m**2  # a new landmark's height prior (ground at the truth here)
        errors[k] = np.linalg.solve(info, np.einsum("kij,kj->i", A, cams)) - point
    return errors.mean(axis=0), float(errors[:, 2].std())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sigma-mrad", type=float, default=3.8, help="ray direction noise per axis, mrad")
    ap.add_argument("--trials", type=int, default=4000)
    ap.add_argument("--corrected", action="store_true", help="take 2 sigma^2 d d^T off each ray's projector")
    a = ap.parse_args()
    rng = np.random.default_rng(0)
    for n, baseline in [(11, 9.0), (15, 12.0), (30, 24.0), (11, 44.0)]:
        m, sd = mean_error(n, baseline, a.sigma_mrad * 1e-3, a.corrected, a.trials, rng)
        print(f"{n:3d} views over {baseline:4.0f} m: mean error N {m[0]:+.3f} E {m[1]:+.3f} D {m[2]:+.3f} m; down one sigma {sd:.3f} m")


if __name__ == "__main__":
    main()
