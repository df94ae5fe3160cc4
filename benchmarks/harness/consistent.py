"""A map-consistent reference: a recording's reference poses refined until every scan fits the
map of all the others.

Why: a reference from LiDAR-inertial odometry carries errors of its own. The BALM sample's
``alidarPose.csv`` is what BALM 2.0's ``benchmark_realworld`` reads as *the initial poses* of its
bundle adjustment; on the sample's first 23 scans (the sensor held nearly still) it puts scan 21
~20 mm away from where GICP and kentreg put it, registering the two scans directly (they agree
with each other to 5 mm). An ATE against such a reference is floored near its own error (~10 mm
on the sample), which hides a difference of a few millimetres between two odometry models. A
scan registered to the map of all the others moves by what the data say, not by what one
odometry chained.

How: rounds of leave-one-out registration. In a round every scan is registered (small_gicp's
GICP, an independent method: kentreg's models are what is judged) to the union of all other
scans at their current poses, from its current pose; the new poses replace the old together
(Jacobi) and are re-anchored so the first scan keeps its reference pose (the gauge). Rounds stop
when no pose moves more than ``tol`` or after ``max_rounds``. What is left moves by a few tenths
of a millimetre a round (GICP's correspondences among the re-posed maps): the precision of such a
reference is measured by building it at two voxel sizes and comparing (the benchmark states it).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass
class ConsistentReference:
    """Refined poses ``T_world_lidar`` (N, 4, 4) and how the rounds went."""

    poses: FloatArray
    voxel: float
    tol: float
    #: Per round: the median and largest translation a pose moved (m).
    moved_m: list[tuple[float, float]] = field(default_factory=list)

    @property
    def converged(self) -> bool:
        """Whether the last round moved no pose more than ``tol``."""
        return bool(self.moved_m) and self.moved_m[-1][1] <= self.tol


def map_consistent_poses(
    clouds: Sequence[FloatArray], T_reference: FloatArray, voxel: float = 0.1,
    max_rounds: int = 12, tol: float = 5e-4, threads: int = 1,
) -> ConsistentReference:  # fmt: skip
    """Refine ``T_reference`` (N, 4, 4) so every cloud (sensor frame, (M_i, 3)) fits the others.

    ``voxel``: GICP's downsampling and covariance scale (m), finer than the scans' own
    sampling so the refined map is sharper than any one scan; the correspondence distance is
    three voxels, as the references move by centimetres, not decimetres. ``tol`` (m): a round in
    which no pose moves more than this ends the refinement.
    """
    import small_gicp  # a benchmark dependency (setup.py's bench extra)

    if len(clouds) != len(T_reference) or len(clouds) < 3:
        raise ValueError('need one pose per cloud, and at least three clouds')
    sampled = [small_gicp.voxelgrid_sampling(np.asarray(c, float), voxel).points()[:, :3]
               for c in clouds]  # fmt: skip
    sources = [small_gicp.preprocess_points(np.asarray(c, float), downsampling_resolution=voxel,
                                            num_threads=threads)[0] for c in clouds]  # fmt: skip
    poses = np.array(T_reference, dtype=float)
    anchor = poses[0].copy()
    out = ConsistentReference(poses, voxel, tol)
    for _ in range(max_rounds):
        new = poses.copy()
        for i in range(len(clouds)):
            others = np.concatenate([
                p @ poses[j][:3, :3].T + poses[j][:3, 3] for j, p in enumerate(sampled) if j != i
            ])  # fmt: skip
            target, tree = small_gicp.preprocess_points(
                others, downsampling_resolution=voxel, num_threads=threads
            )
            new[i] = small_gicp.align(
                target, sources[i], tree, init_T_target_source=poses[i],
                registration_type='GICP', max_correspondence_distance=3 * voxel,
                num_threads=threads,
            ).T_target_source  # fmt: skip
        new = anchor @ np.linalg.inv(new[0]) @ new
        new[0] = anchor  # exactly, not to the rounding of the product
        moved = np.linalg.norm(new[:, :3, 3] - poses[:, :3, 3], axis=1)
        poses = new
        out.moved_m.append((float(np.median(moved)), float(moved.max())))
        if moved.max() <= tol:
            break
    out.poses = poses
    return out
