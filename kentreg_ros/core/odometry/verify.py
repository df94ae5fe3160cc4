"""The verify stage: register from the prediction, judge it, and choose the step's pose.

:class:`Verifier` is the only place a pose is chosen: the registration from the prediction, or,
when that is doubtful, the best-fitting plausible pose of the start-free search (the one nearest
the prediction among those fitting about equally), or a fall-back to the prediction. Its
:class:`Outcome` is the step's pose in the model frame and its health.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from kentreg_ros.core.config import KentRegConfig, Mode, SearchMode
from kentreg_ros.core.errors import KentRegError
from kentreg_ros.core.geometry import rotation_angle
from kentreg_ros.core.odometry.step import Health
from kentreg_ros.core.registration import RegistrationResult, Status, register
from kentreg_ros.core.registration.verify import Candidate, FitGates, choose_pose
from kentreg_ros.core.scan import PreparedScan

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class Outcome:
    """The pose a step takes in the model frame, or a fall-back to the prediction."""

    result: RegistrationResult | None
    T: FloatArray
    fit: float
    health: Health
    message: str
    searched: bool = False

    @classmethod
    def fell_back(
        cls, reason: str, result: RegistrationResult | None = None, searched: bool = False
    ) -> Outcome:
        """Fall back to the prediction; ``result`` (the rejected estimate) is kept for
        inspection."""
        message = f'Fell back to the prediction: {reason}.'
        return cls(result, np.eye(4), float('nan'), Health.FELL_BACK, message, searched)

    @classmethod
    def rejected(cls, reason: str) -> Outcome:
        """An unusable cloud (``reason``: why): the pose is the prediction."""
        message = f'Rejected the scan: {reason} The pose is the prediction.'
        return cls(None, np.eye(4), float('nan'), Health.REJECTED, message)

    @classmethod
    def first(cls) -> Outcome:
        """The first scan: it becomes the model, at the initial pose."""
        return cls(
            None, np.eye(4), float('nan'), Health.FIRST, 'First scan: it becomes the model.'
        )

    def with_anchor(self, anchor: FloatArray) -> Outcome:
        """This outcome with ``anchor`` (the model pose's own error against the model,
        :attr:`~kentreg_ros.core.odometry.models.ModelStrategy.anchor`) added to its result's
        covariance: the step's error is its registration's and the model pose's together."""
        if self.result is None or not self.health.accepted or not np.any(anchor):
            return self
        covariance = np.asarray(self.result.covariance, dtype=np.float64) + anchor
        return replace(self, result=replace(self.result, covariance=covariance))

    def stage_timings(self, stages: tuple[str, ...]) -> dict[str, float]:
        """Milliseconds of those ``stages`` of the registration used (none without one)."""
        timings = self.result.timings if self.result is not None else {}
        return {stage: timings[stage] for stage in stages if stage in timings}


def _own_health(result: RegistrationResult) -> Health:
    return Health.DEGENERATE if result.status == Status.DEGENERATE else Health.OK


class Verifier:
    """Judges a registration and chooses the step's pose: the only place that chooses.

    A registration from the prediction is *doubtful* when it failed, breaks the speed limits
    (``odometry.max_*_speed``) or fits clearly worse than the recent accepted steps
    (``odometry.doubt_ratio`` of the median of ``fits``; of 1, the best fit there is, before
    the first accepted step). Then the start-free search runs too
    and :func:`~kentreg_ros.core.registration.verify.choose_pose` chooses among the plausible
    poses, preferring the one nearest the prediction among those that fit about equally.

    A registration that raises a :class:`~kentreg_ros.core.errors.KentRegError` or a
    ``LinAlgError`` (a scene it cannot solve) falls back; any other exception is a bug and
    propagates, so that the caller counts it as an error instead of a fall-back.
    """

    def __init__(self, config: KentRegConfig) -> None:
        self.config = config

    def implausible(self, T_model_curr: FloatArray, gap_ns: int) -> str:
        """Why a step breaks the speed limits over ``gap_ns``, or '' if it does not."""
        if gap_ns <= 0:
            return ''
        odo = self.config.odometry
        gap = gap_ns * 1e-9
        angle = np.degrees(rotation_angle(T_model_curr[:3, :3]))
        dist = float(np.linalg.norm(T_model_curr[:3, 3]))
        if angle > odo.max_angular_speed_deg * gap:
            return (
                f'the step turns {angle:.1f} deg in {gap:.3f} s, faster than '
                f'odometry.max_angular_speed_deg={odo.max_angular_speed_deg}'
            )
        if dist > odo.max_linear_speed * gap:
            return (
                f'the step moves {dist:.2f} m in {gap:.3f} s, faster than '
                f'odometry.max_linear_speed={odo.max_linear_speed}'
            )
        return ''

    def doubt(self, result: RegistrationResult, why_implausible: str, fits: list[float]) -> str:
        """Why the registration from the prediction is doubtful, or '' if it is not."""
        if result.status == Status.FAILED:
            return f'it failed ({result.message})'
        if why_implausible:
            return why_implausible
        if not np.isfinite(result.fit):
            return ''  # paper mode: no fit to judge by
        # With no accepted step yet, the best fit any pose can have (1, every point on a
        # matching surface) stands in for the recent median. A wrong minimum loses whole
        # families of surfaces, so it fits far below a right one (docs/notes-odometry.md,
        # test_first_fit_separates_right_from_wrong_minima): only a first fit below
        # doubt_ratio pays for the start-free search.
        median = float(np.median(fits)) if fits else 1.0
        ratio = self.config.odometry.doubt_ratio
        if result.fit < ratio * median:
            of = f'the recent median {median:.2f}' if fits else 'a perfect fit (no step yet)'
            return f'its fit {result.fit:.2f} is below {ratio} x {of}'
        return ''

    def choose(
        self,
        scan: PreparedScan,
        model: PreparedScan,
        T_pred: FloatArray,
        gap_ns: int,
        fits: list[float],
    ) -> Outcome:
        """Register ``scan`` against ``model`` from ``T_pred``; search when that is doubtful;
        return the step's pose in the model frame."""
        cfg = self.config
        try:
            first = register(scan, model, init=T_pred, config=cfg, global_search=False)
        except (KentRegError, np.linalg.LinAlgError) as exc:
            return Outcome.fell_back(f'the registration raised {type(exc).__name__}: {exc}')
        why = self.implausible(first.T_target_source, gap_ns)
        doubt = self.doubt(first, why, fits)
        if not doubt:
            return Outcome(
                first, first.T_target_source, first.fit, _own_health(first), first.message
            )
        candidates: list[Candidate[RegistrationResult]] = []
        if first.status != Status.FAILED and not why:
            candidates.append(Candidate(first.T_target_source, first.fit, first))
        searched = cfg.mode == Mode.ROBUST and cfg.search.mode != SearchMode.NEVER
        if searched:
            candidates += self._search(scan, model, gap_ns)
        if not candidates:
            reason = (
                f'the registration from it was doubtful ({doubt}) and no plausible pose was found'
            )
            return Outcome.fell_back(reason, first, searched)
        spacing = max(scan.voxel_size, model.voxel_size)
        gate = 2.0 * FitGates.for_spacing(spacing).distance if spacing > 0.0 else 0.0
        choice = choose_pose(
            candidates,
            scan.points,
            gate=gate,
            ratio=cfg.search.ambiguity_ratio,
            prior=T_pred,
            preferred=candidates[0] if not candidates[0].searched else None,
        )
        if np.isfinite(first.fit) and choice.best_fit < cfg.odometry.min_fit:
            return Outcome.fell_back(
                f'the best pose found fits {choice.best_fit:.2f} < odometry.min_fit='
                f'{cfg.odometry.min_fit} ({doubt})',
                first,
                searched,
            )
        chosen = choice.chosen
        if choice.rivals:
            health = Health.AMBIGUOUS
            message = (
                f'{len(choice.rivals) + 1} distinct poses fit about equally (fit '
                f'{chosen.fit:.2f}); used the one nearest the prediction. Searched because '
                f'{doubt}.'
            )
        elif chosen.searched:
            health = Health.RECOVERED
            message = (
                f'Recovered: the registration from the prediction was doubtful ({doubt}); the '
                f'search found a pose fitting {chosen.fit:.2f} (it fitted {first.fit:.2f}).'
            )
        else:
            health = _own_health(chosen.origin)
            message = f'{chosen.origin.message} Confirmed by a search ({doubt}).'
        return Outcome(chosen.origin, chosen.T, chosen.fit, health, message, searched)

    def _search(
        self, scan: PreparedScan, model: PreparedScan, gap_ns: int
    ) -> list[Candidate[RegistrationResult]]:
        """The plausible poses of the start-free search (its best and its alternatives)."""
        try:
            found = register(scan, model, init=np.eye(4), config=self.config, global_search=True)
        except (KentRegError, np.linalg.LinAlgError) as exc:
            logger.warning('The search raised %s: %s', type(exc).__name__, exc)
            return []
        if found.status == Status.FAILED:
            return []
        # An alternative's result is the search's with that pose's own covariance (the step
        # reports the uncertainty of the pose it takes; the pose itself is the candidate's).
        own = [found] + [replace(found, covariance=cov) for cov in found.alternative_covariances]
        return [
            Candidate(T, fit, own[i] if i < len(own) else found, searched=True)
            for i, (T, fit) in enumerate([(found.T_target_source, found.fit), *found.alternatives])
            if not self.implausible(T, gap_ns)
        ]

    def judge_round(
        self, result: RegistrationResult, before: Outcome, gap_ns: int
    ) -> Outcome | None:
        """The outcome of a registration after deskewing again, from ``before``'s pose, or None
        when it is no better than ``before`` (it failed, fits clearly worse, or breaks the
        speed limits). Its own status decides ok or degenerate; a pose found by the search, or
        chosen among ambiguous ones, keeps saying so."""
        if (
            result.status == Status.FAILED
            or not result.fit >= before.fit * self.config.search.ambiguity_ratio
            or self.implausible(result.T_target_source, gap_ns)
        ):
            return None
        health, message = _own_health(result), f'{result.message} (re-registered after deskewing)'
        if health is Health.OK and before.health in (Health.RECOVERED, Health.AMBIGUOUS):
            health, message = before.health, before.message
        return Outcome(
            result, result.T_target_source, result.fit, health, message, before.searched
        )
