"""Benchmarks of kentreg_ros against other registration methods (not part of the package)."""
