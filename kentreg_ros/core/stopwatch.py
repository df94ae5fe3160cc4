"""Stage timings as one object instead of a ``timings`` dict threaded through signatures.

A :class:`Stopwatch` accumulates milliseconds per stage name; a stage is timed with
``with watch('refine'): ...``, which adds to what the stage already took (a stage run twice in
one registration, e.g. for two candidate poses, reports their sum). :meth:`Stopwatch.as_dict`
is what results and steps report (``RegistrationResult.timings``, ``OdometryStep.timings``).
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager


class Stopwatch:
    """Milliseconds per stage, accumulated.

    Examples
    --------
    >>> watch = Stopwatch()
    >>> with watch('rotation'):
    ...     pass
    >>> sorted(watch.as_dict())
    ['rotation']
    """

    def __init__(self) -> None:
        self._ms: dict[str, float] = {}
        self._start = time.perf_counter()

    @contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        """Time the block as ``stage`` (added to what it took before)."""
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.add(stage, (time.perf_counter() - t0) * 1e3)

    def add(self, stage: str, ms: float) -> None:
        """Add ``ms`` milliseconds to ``stage``."""
        self._ms[stage] = self._ms.get(stage, 0.0) + float(ms)

    def merge(self, other: Mapping[str, float], prefix: str = '') -> None:
        """Add every stage of ``other`` (another watch's :meth:`as_dict`), names prefixed."""
        for stage, ms in other.items():
            self.add(prefix + stage, ms)

    def elapsed_ms(self) -> float:
        """Milliseconds since the watch was made."""
        return (time.perf_counter() - self._start) * 1e3

    def as_dict(self) -> dict[str, float]:
        """The stages and their milliseconds (a copy)."""
        return dict(self._ms)

    def __contains__(self, stage: object) -> bool:
        return stage in self._ms

    def __getitem__(self, stage: str) -> float:
        return self._ms[stage]
