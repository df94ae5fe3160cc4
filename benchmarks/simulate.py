"""Write a re-simulated sequence (``benchmarks/harness/simulator.py``) as a scan folder.

``scan_<i>.pcd`` (float32 x y z, and ``t`` with sweeps) and ``alidarPose.csv`` with the exact
poses (BALM format, stamped at the input's scan rate), which ``kentreg_replay`` and
``benchmarks/odometry.py`` read like any recording.

Usage::

    python3 benchmarks/simulate.py --out /tmp/sim_0.6 --step 0.6 --seed 0
"""

from __future__ import annotations

import argparse
import logging
import sys
from argparse import RawDescriptionHelpFormatter
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.harness.simulator import (  # noqa: E402  # noqa: E402
    DEFAULT_INPUT,
    WORLD_VOXEL,
    Sensor,
    build_world,
    motion_stats,
    simulate,
)
from kentreg_ros.io.scanfiles import write_pcd  # noqa: E402

FloatArray = NDArray[np.float64]
logger = logging.getLogger('simulate')


def write_balm_poses(path: Path, T: FloatArray, stamps_s: FloatArray) -> None:
    """``alidarPose.csv``: the 3x4 ``[R | t]`` and ``0,0,0,<time>`` per pose (17 digits)."""
    lines: list[str] = []
    for Ti, ts in zip(T, stamps_s, strict=True):
        lines.extend(','.join(f'{v:.17g}' for v in row) + ',' for row in Ti[:3])
        lines.append(f'0,0,0,{ts:.9f},')
    path.write_text('\n'.join(lines) + '\n')


SWEEP = 's per sweep, points timed in a field t; 0: all at the stamp'
SENSOR_OPTIONS = {'occlusion_bin': 'deg', 'beam_bin': 'deg', 'range_noise': 'm, 1 sigma',
                  'min_range': 'm', 'max_range': 'm', 'sweep_period': SWEEP}  # fmt: skip


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=RawDescriptionHelpFormatter)
    p.add_argument('--input', type=Path, default=DEFAULT_INPUT, help='recording to re-simulate')
    p.add_argument('--out', type=Path, required=True, help='scan folder to write')
    p.add_argument('--step', type=float, default=0.6, help='metres per scan (default 0.6)')
    p.add_argument('--yaw-amplitude', type=float, default=0.0, help='yaw oscillation, deg')
    p.add_argument('--yaw-period', type=float, default=9.0, help='yaw oscillation period, scans')
    p.add_argument('--seed', type=int, default=0, help='seed of the sampling and the noise')
    p.add_argument('--world-voxel', type=float, default=WORLD_VOXEL, help='world thinning, m')
    for name, unit in SENSOR_OPTIONS.items():
        value, flag = getattr(Sensor(), name), '--' + name.replace('_', '-')
        p.add_argument(flag, type=float, default=value, help=f'{unit} ({value})')
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format='%(name)s: %(message)s')
    world = build_world(args.input, args.world_voxel)
    sensor = Sensor(**{name: getattr(args, name) for name in SENSOR_OPTIONS})
    yaw = {'yaw_amplitude': args.yaw_amplitude, 'yaw_period': args.yaw_period}
    scans, gt = simulate(world, args.step, args.seed, sensor, **yaw)
    args.out.mkdir(parents=True, exist_ok=True)
    for i, scan in enumerate(scans):
        write_pcd(args.out / f'scan_{i:04d}.pcd', scan.points.astype(np.float32), scan.extras)
    T = gt.trajectory.T_world_sensor
    write_balm_poses(args.out / 'alidarPose.csv', T, np.asarray(gt.trajectory.stamps_ns) * 1e-9)
    stats, counts = motion_stats(T), [len(scan.points) for scan in scans]
    logger.info(
        'world %d points; %d scans of %d-%d points; step %.2f m, rotation per scan median '
        '%.1f deg, max %.1f deg -> %s', len(world.points), len(scans), min(counts), max(counts),
        stats['step_median_m'], stats['rotation_median_deg'], stats['rotation_max_deg'], args.out,
    )  # fmt: skip
    return 0


if __name__ == '__main__':
    sys.exit(main())
