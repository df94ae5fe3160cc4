"""Tests of kentreg_ros.eval.plotting: the trajectory figure is written as a real PNG."""

from __future__ import annotations

import logging
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


def read_png(path: Path) -> np.ndarray:
    """The image, after checking it is a PNG file."""
    from matplotlib.image import imread

    assert path.read_bytes().startswith(PNG_SIGNATURE)
    return imread(path)


def ink(image: np.ndarray, colour: str) -> int:
    """Pixels drawn in ``colour`` (anti-aliased edges aside)."""
    from matplotlib.colors import to_rgb

    return int((np.abs(image[..., :3] - np.array(to_rgb(colour))).max(axis=-1) < 0.02).sum())


#: A line across a panel is thousands of pixels at 120 dpi; a legend entry about a hundred.
LINE_PIXELS = 500


def test_plot_trajectory_draws_the_estimate_alone_in_one_panel(tmp_path: Path) -> None:
    out = plot_trajectory(tmp_path / 'est.png', circle_trajectory(40, 10.0))
    assert out == tmp_path / 'est.png'
    image = read_png(out)
    assert image.shape[:2] == (round(6.5 * 120), 7 * 120)  # one panel, 7 x 6.5 in at 120 dpi
    assert ink(image, 'tab:blue') > LINE_PIXELS  # the estimate
    assert ink(image, 'tab:gray') < LINE_PIXELS  # no ground truth
    assert ink(image, 'tab:red') == ink(image, 'tab:green') == 0  # no error panels


def test_plot_trajectory_draws_ground_truth_and_one_panel_per_error_series(
    tmp_path: Path,
) -> None:
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
    image = read_png(out)
    assert image.shape[:2] == (6 * 120, 13 * 120)  # top view plus the error column
    for colour in ('tab:blue', 'tab:gray', 'tab:red', 'tab:green'):  # est, gt, e_R, e_t
        assert ink(image, colour) > LINE_PIXELS, colour
    only_rotation = read_png(
        plot_trajectory(tmp_path / 'r.png', T_est, T_gt, e_R_deg=errors['e_R_deg'])
    )
    assert ink(only_rotation, 'tab:red') > LINE_PIXELS and ink(only_rotation, 'tab:green') == 0


def test_plot_trajectory_rejects_bad_error_series(tmp_path: Path) -> None:
    T = circle_trajectory(10, 5.0)
    with pytest.raises(ValueError, match=r'Expected `e_t` to have shape \(M,\), got \(9, 1\)\.'):
        plot_trajectory(tmp_path / 'bad.png', T, e_t=np.zeros((9, 1)))
    with pytest.raises(ValueError, match=r'Expected `T_gt` to have shape \(N, 4, 4\)'):
        plot_trajectory(tmp_path / 'bad.png', T, np.eye(4))
    assert not (tmp_path / 'bad.png').exists()


def test_plot_trajectory_draws_the_map_behind_the_paths(tmp_path: Path) -> None:
    """A wall of map points around the circle darkens pixels the plain plot leaves white, and
    a map of the wrong shape is refused before anything is written."""
    T = circle_trajectory(40, 10.0)
    angle = np.linspace(0.0, 2.0 * np.pi, 20_000)
    wall = np.column_stack([14.0 * np.cos(angle), 14.0 * np.sin(angle), np.linspace(0, 3, 20_000)])
    plain = read_png(plot_trajectory(tmp_path / 'plain.png', T))
    with_map = read_png(plot_trajectory(tmp_path / 'map.png', T, map_points=wall))
    assert plain.shape == with_map.shape
    darker = (with_map[..., :3].mean(axis=-1) < plain[..., :3].mean(axis=-1) - 0.1).sum()
    assert darker > LINE_PIXELS
    assert ink(with_map, 'tab:blue') > LINE_PIXELS  # the path is still drawn on top
    with pytest.raises(ValueError, match=r'Expected `map_points` to have shape \(P, 3\)'):
        plot_trajectory(tmp_path / 'bad.png', T, map_points=np.zeros((5, 2)))
    assert not (tmp_path / 'bad.png').exists()


def test_plot_trajectory_with_a_map_and_equal_axes_logs_nothing(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, capfd: pytest.CaptureFixture[str]
) -> None:
    """The view framing the paths and the bulk of the map keeps x and y at one scale without
    matplotlib overriding it: before, fixed limits with ``adjustable='datalim'`` made it log
    "Ignoring fixed x limits to fulfill fixed data aspect..." at every draw (twice per
    ``kentreg_replay`` run). The framing still holds: every path point and most of the map are
    in view, a stray far return is not, and the view has the panel's aspect at equal scales."""
    T_gt = circle_trajectory(40, 10.0)
    T_est = circle_trajectory(40, 10.0, noise=0.2)
    rng = np.random.default_rng(3)
    wall = np.column_stack(
        [rng.uniform(-14.0, 14.0, 5000), rng.uniform(-3.0, 3.0, 5000), rng.uniform(0, 3, 5000)]
    )
    stray = np.array([[500.0, 0.0, 1.0]])
    errors = rpe(T_est, T_gt)
    captured = {}
    import matplotlib.figure

    savefig = matplotlib.figure.Figure.savefig

    def keep_axes(fig: matplotlib.figure.Figure, *args: object, **kwargs: object) -> None:
        savefig(fig, *args, **kwargs)
        captured['ax'] = fig.axes[0]

    with caplog.at_level(logging.DEBUG, logger='matplotlib'), pytest.MonkeyPatch.context() as mp:
        mp.setattr(matplotlib.figure.Figure, 'savefig', keep_axes)
        plot_trajectory(
            tmp_path / 'map.png',
            T_est,
            T_gt,
            e_R_deg=errors['e_R_deg'],
            e_t=errors['e_t'],
            map_points=np.vstack([wall, stray]),
        )
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert warnings == [], [r.getMessage() for r in warnings]
    assert capfd.readouterr().err == ''
    ax = captured['ax']
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    paths = np.vstack([T_est[:, :2, 3], T_gt[:, :2, 3]])
    assert (paths[:, 0] > x0).all() and (paths[:, 0] < x1).all()
    assert (paths[:, 1] > y0).all() and (paths[:, 1] < y1).all()
    assert x1 < 100.0  # the stray return at x = 500 m is out of view
    assert x0 < -14.0 * 0.9 and x1 > 14.0 * 0.9  # the wall's extent is in view
    bbox = ax.get_window_extent()
    np.testing.assert_allclose((y1 - y0) / (x1 - x0), bbox.height / bbox.width, rtol=0.02)
