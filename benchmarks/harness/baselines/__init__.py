"""Baselines with no maintained Python implementation: NDT (Magnusson) and correntropy ICP."""
