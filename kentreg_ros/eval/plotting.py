"""Trajectory plots for evaluation runs (matplotlib, imported lazily; not part of the core).

:func:`plot_trajectory` draws any estimate over any reference; :func:`plot_run` draws an odometry
run as ``kentreg_replay`` writes it to ``trajectory.png``.

matplotlib is an optional dependency (extras ``test`` and ``bench``). The figure is drawn with
the object-oriented API on an Agg canvas, so no pyplot state or global backend is touched and
the function is safe in headless processes and worker threads.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kentreg_ros.eval.metrics import as_poses

if TYPE_CHECKING:
    from matplotlib.axes import Axes

    from kentreg_ros.eval.report import Evaluation
    from kentreg_ros.eval.run import OdometryRun

logger = logging.getLogger(__name__)

_EST_COLOUR = 'tab:blue'
_GT_COLOUR = 'tab:gray'
#: Colour map of the map's points by height, light to dark so the paths stay on top.
_MAP_CMAP = 'Greys'
#: Map points drawn at most (an even subsample beyond): enough to show every wall of a
#: building-sized map at 120 dpi, few enough to keep the PNG small and fast to write.
MAX_MAP_POINTS = 200_000


def _as_series(values: ArrayLike, name: str) -> NDArray[np.float64]:
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f'Expected `{name}` to be numeric, got {exc}.') from exc
    if arr.ndim != 1:
        raise ValueError(f'Expected `{name}` to have shape (M,), got {arr.shape}.')
    return arr


def _plot_top_view(
    ax: Axes, xy: NDArray[np.float64], label: str, colour: str, *, linewidth: float, alpha: float
) -> None:
    ax.plot(xy[:, 0], xy[:, 1], color=colour, label=label, linewidth=linewidth, alpha=alpha)
    ax.plot(*xy[0], marker='o', color=colour, markersize=7, linestyle='none')
    ax.plot(*xy[-1], marker='s', color=colour, markersize=7, linestyle='none')


def _figure(n_series: int) -> tuple[Any, Any, Any]:
    """A figure with the top view on the left and ``n_series`` error panels on the right (its
    grid; None without panels), and the top view's axes."""
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as exc:
        raise ImportError(
            'plot_trajectory needs matplotlib: pip install matplotlib '
            "(or the package's `bench` / `test` extra)."
        ) from exc
    grid = None
    if n_series:
        fig = Figure(figsize=(13.0, 6.0), layout='constrained')
        grid = fig.add_gridspec(n_series, 2, width_ratios=(1.1, 1.0))
        ax_top = fig.add_subplot(grid[:, 0])
    else:
        fig = Figure(figsize=(7.0, 6.5), layout='constrained')
        ax_top = fig.add_subplot()
    FigureCanvasAgg(fig)
    return fig, grid, ax_top


def _map_sample(map_points: ArrayLike) -> NDArray[np.float64]:
    """The finite map points, evenly subsampled to :data:`MAX_MAP_POINTS`."""
    cloud = np.asarray(map_points, dtype=np.float64)
    if cloud.ndim != 2 or cloud.shape[1] != 3:
        raise ValueError(f'Expected `map_points` to have shape (P, 3), got {cloud.shape}.')
    cloud = cloud[np.isfinite(cloud).all(axis=1)]
    if len(cloud) > MAX_MAP_POINTS:
        cloud = cloud[:: -(-len(cloud) // MAX_MAP_POINTS)]
    return cloud


def _draw_map(ax: Any, cloud: NDArray[np.float64]) -> None:
    """The map behind the paths: points shaded by height (darker is higher)."""
    z_lo, z_hi = np.percentile(cloud[:, 2], [2.0, 98.0])
    ax.scatter(
        cloud[:, 0],
        cloud[:, 1],
        c=cloud[:, 2],
        cmap=_MAP_CMAP,
        vmin=z_lo - 0.5 * (z_hi - z_lo),  # the lowest points mid-grey, not white
        vmax=z_hi,
        s=0.3,
        alpha=0.5,
        linewidths=0,
        rasterized=True,
        zorder=0,
        label=f'map ({len(cloud)} points)',
    )


def _frame_paths_and_map(
    ax: Any, est: NDArray[np.float64], gt: NDArray[np.float64] | None, cloud: NDArray[np.float64]
) -> None:
    """The view: the paths and the bulk of the map; a few stray far returns must not shrink
    the paths to a dot."""
    # The scatter put every map point into the data limits: they are
    # replaced by that box, and the view limits stay automatic (with the axes' margins),
    # so the equal aspect below can widen one of them to the panel's shape. Fixed limits
    # would leave it nothing to adjust: matplotlib then overrides them and logs "Ignoring
    # fixed x limits ..." at every draw.
    paths = est[:, :2, 3] if gt is None else np.vstack([est[:, :2, 3], gt[:, :2, 3]])
    lo = np.minimum(paths.min(axis=0), np.percentile(cloud[:, :2], 1.0, axis=0))
    hi = np.maximum(paths.max(axis=0), np.percentile(cloud[:, :2], 99.0, axis=0))
    ax.ignore_existing_data_limits = True
    ax.update_datalim(np.array([lo, hi]))
    ax.autoscale_view()


def _plot_error_panels(
    fig: Any, grid: Any, series: list[tuple[NDArray[np.float64], str, str]]
) -> None:
    """One panel per error series on the right, against the pair index."""
    ax_prev = None
    for row, (values, label, colour) in enumerate(series):
        ax = fig.add_subplot(grid[row, 1], sharex=ax_prev)
        index = np.arange(values.size)
        ax.plot(index, values, color=colour, linewidth=1.0, marker='.', markersize=3)
        finite = values[np.isfinite(values)]
        if finite.size:
            mean = float(finite.mean())
            ax.axhline(
                mean, color='black', linestyle='--', linewidth=0.8, label=f'mean {mean:.3g}'
            )
            ax.legend(loc='upper right')
        ax.set_ylabel(label)
        ax.set_ylim(bottom=0.0)
        ax.grid(True, alpha=0.3)
        if row == len(series) - 1:
            ax.set_xlabel('pair index')
        else:
            ax.tick_params(labelbottom=False)
        ax_prev = ax


def plot_trajectory(
    path_png: str | os.PathLike[str],
    T_est: ArrayLike,
    T_gt: ArrayLike | None = None,
    *,
    e_R_deg: ArrayLike | None = None,
    e_t: ArrayLike | None = None,
    title: str = '',
    map_points: ArrayLike | None = None,
) -> Path:
    """Write a PNG with the top view of a trajectory and, optionally, its per-pair errors.

    The left panel shows the x-y positions of the estimate over the ground truth with equal axes
    and start (circle) and end (square) markers. The ground truth is drawn as given: align the
    trajectories first (e.g. with :func:`kentreg_ros.eval.alignment.ate`'s ``T_gt_est``) if they
    do not share a world frame. Each given error series adds a panel on the right, plotted
    against the pair index.

    Parameters
    ----------
    path_png : str or os.PathLike
        Output file; its directory must exist.
    T_est : array_like, shape (N, 4, 4)
        Estimated poses ``T_world_sensor``.
    T_gt : array_like, shape (M, 4, 4), optional
        Ground-truth poses in the same world frame.
    e_R_deg : array_like, shape (P,), optional
        Rotation error of each pair in degrees (e.g. :func:`~kentreg_ros.eval.metrics.rpe`'s
        ``e_R_deg``).
    e_t : array_like, shape (P,), optional
        Translation error of each pair in metres.
    title : str
        Figure title; none if empty.
    map_points : array_like, shape (P, 3), optional
        A map in the same world frame (e.g. the replay's run map), drawn behind the paths as
        points shaded by height (darker is higher); evenly subsampled to
        :data:`MAX_MAP_POINTS`.

    Returns
    -------
    pathlib.Path
        ``path_png``.

    Raises
    ------
    ImportError
        matplotlib is not installed.
    ValueError
        Invalid poses or error series of the wrong shape.
    """
    est = as_poses(T_est, 'T_est')
    gt = None if T_gt is None else as_poses(T_gt, 'T_gt')
    cloud = None if map_points is None else _map_sample(map_points)
    series: list[tuple[NDArray[np.float64], str, str]] = []
    if e_R_deg is not None:
        series.append((_as_series(e_R_deg, 'e_R_deg'), 'rotation error $e_R$ [deg]', 'tab:red'))
    if e_t is not None:
        series.append((_as_series(e_t, 'e_t'), 'translation error $e_t$ [m]', 'tab:green'))

    path = Path(path_png)
    fig, grid, ax_top = _figure(len(series))

    if cloud is not None and len(cloud):
        _draw_map(ax_top, cloud)
    if gt is not None:
        _plot_top_view(ax_top, gt[:, :2, 3], 'ground truth', _GT_COLOUR, linewidth=2.5, alpha=0.8)
    _plot_top_view(ax_top, est[:, :2, 3], 'estimate', _EST_COLOUR, linewidth=1.5, alpha=1.0)
    # Proxy entries so the legend explains the markers once, in black.
    ax_top.plot([], [], marker='o', color='black', linestyle='none', label='start')
    ax_top.plot([], [], marker='s', color='black', linestyle='none', label='end')
    if cloud is not None and len(cloud):
        _frame_paths_and_map(ax_top, est, gt, cloud)
    ax_top.set_aspect('equal', adjustable='datalim')
    ax_top.set_xlabel('x [m]')
    ax_top.set_ylabel('y [m]')
    ax_top.set_title('top view (x-y)')
    ax_top.grid(True, alpha=0.3)
    ax_top.legend(loc='best')

    if series:
        _plot_error_panels(fig, grid, series)
    if title:
        fig.suptitle(title)
    fig.savefig(path, dpi=120)
    logger.debug('Wrote trajectory plot %s', path)
    return path


def plot_run(
    path_png: str | os.PathLike[str],
    run: OdometryRun,
    evaluation: Evaluation | None = None,
    *,
    title: str = '',
) -> Path:
    """Write the PNG of an odometry run (:func:`plot_trajectory`).

    Without an evaluation the estimate is drawn alone. With one, the estimated poses that have
    a reference are mapped into the reference frame by the ATE alignment ``T_gt_est`` (the
    identity below 3 poses) and drawn over it, with the per-pair errors on the right. The run's
    map, when it was accumulated, is drawn behind the paths (aligned the same way).

    Raises
    ------
    ImportError
        matplotlib is not installed.
    """
    cloud = None
    if run.map is not None and len(run.map):
        cloud = run.map.points.astype(np.float64)
    if evaluation is None:
        return plot_trajectory(path_png, run.poses, title=title, map_points=cloud)
    ate = evaluation.metrics['ate']
    T_gt_est = np.asarray(ate['T_gt_est']) if ate is not None else np.eye(4)
    if cloud is not None:  # the map is in the estimate's frame: align it with the poses
        cloud = cloud @ T_gt_est[:3, :3].T + T_gt_est[:3, 3]
    pairs = evaluation.metrics['pairs']
    return plot_trajectory(
        path_png,
        T_gt_est @ run.poses[evaluation.scan_rows],
        evaluation.T_gt,
        e_R_deg=pairs['e_R_deg'],
        e_t=pairs['e_t_m'],
        title=title,
        map_points=cloud,
    )
