"""A scan prepared once for registration: voxels (:mod:`.voxels`), normals (:mod:`.normals`),
their clusters as a Kent mixture (:mod:`.clusters`), the neighbour index (:mod:`.neighbors`)."""

from kentreg_ros.core.scan.prepared import PreparedScan, prepare_scan

__all__ = ['PreparedScan', 'prepare_scan']
