"""The Kent registration: the rotation from the normals' Kent mixtures by EM (:mod:`.em`,
:mod:`.rotations`, :mod:`.search`), the translation from positions (:mod:`.translation`), the
joint refinement (:mod:`.refine`) and the judgement of a pose (:mod:`.verify`); the two recipes
(:mod:`.robust`, :mod:`.paper`) behind one call (:func:`register`)."""

from kentreg_ros.core.registration.register import register
from kentreg_ros.core.registration.result import RegistrationResult, Status

__all__ = ['RegistrationResult', 'Status', 'register']
