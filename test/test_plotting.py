"""Tests of kentreg_ros.eval.plotting: the trajectory figure is written as a real PNG."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from kentreg_ros.eval.metrics import rpe

pytest.importorskip('matplotlib', reason='matplotlib is optional; pip install matplotlib')

from kentreg_ros.eval.plotting import plot_trajectory  # noqa: E402

PNG_SIGNATURE = b'\x89PNG\r\n\x1a\n'


def circle_trajectory(n: int, radius: float, noise: float = 0.0) -> np.ndarray:
    rng = np.random.default_rng(0)
    theta = np.linspace(0.0, 1.5 * np.pi, n)
    yaw = theta + rng.normal(0.0, 0.1 * noise, n)
    T = np.tile(np.eye(4), (n, 1, 1))
    c, s = np.cos(yaw), np.sin(yaw)
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -s, s, c
    T[:, 0, 3] = radius * np.cos(theta) + rng.normal(0.0, noise, n)
    T[:, 1, 3] = radius * np.sin(theta) + rng.normal(0.0, noise, n)
    return T


def assert_png(path: Path) -> None:
    assert path.is_file()
    data = path.read_bytes()
    assert data.startswith(PNG_SIGNATURE)
    assert len(data) > 5_000


def test_plot_trajectory_writes_png_of_estimate_alone(tmp_path: Path) -> None:
    out = plot_trajectory(tmp_path / 'est.png', circle_trajectory(40, 10.0))
    assert out == tmp_path / 'est.png'
    assert_png(out)


def test_plot_trajectory_writes_png_with_ground_truth_and_pair_errors(tmp_path: Path) -> None:
    T_gt = circle_trajectory(60, 10.0)
    T_est = circle_trajectory(60, 10.0, noise=0.2)
    errors = rpe(T_est, T_gt)
    out = plot_trajectory(
        str(tmp_path / 'full.png'),
        T_est,
        T_gt,
        e_R_deg=errors['e_R_deg'],
        e_t=errors['e_t'],
        title='synthetic circle',
    )
    assert_png(out)
    # The error panels make the figure larger than the top view alone.
    alone = plot_trajectory(tmp_path / 'alone.png', T_est, T_gt)
    assert_png(alone)
    assert out.stat().st_size > alone.stat().st_size


def test_plot_trajectory_rejects_bad_error_series(tmp_path: Path) -> None:
    T = circle_trajectory(10, 5.0)
    with pytest.raises(ValueError, match=r'Expected `e_t` to have shape \(M,\), got \(9, 1\)\.'):
        plot_trajectory(tmp_path / 'bad.png', T, e_t=np.zeros((9, 1)))
    with pytest.raises(ValueError, match=r'Expected `T_gt` to have shape \(N, 4, 4\)'):
        plot_trajectory(tmp_path / 'bad.png', T, np.eye(4))
    assert not (tmp_path / 'bad.png').exists()
