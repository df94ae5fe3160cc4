"""Start-free rotation hypotheses from the two clouds' normal-mixture summaries.

The rotation between two scans moves every normal cluster of one onto a cluster of the other.
Each hypothesis aligns the mean direction of one source cluster with that of one target
cluster and turns about it in steps of ``step_deg``: ``K_s * K_t * 360 / step_deg`` rotations
that cover SO(3) wherever some cluster of each cloud correspond (the twist grid). Each is scored
by the overlap of the two mixtures, the integral of the product of their densities, in closed
form for von Mises-Fisher components::

    S(R) = sum_ij w_i v_j int vMF(z; R mu_i, k_i) vMF(z; nu_j, l_j) dz
         = sum_ij w_i v_j C(k_i) C(l_j) / C(|k_i R mu_i + l_j nu_j|),  C(k) = k / (4 pi sinh k),

with the concentrations capped so that a peak is not narrower than the grid step. The score
ranks hypotheses cheaply; it does not decide (symmetric scenes give twins equal scores): the
distinct best are refined by the EM and verified on the points
(:func:`kentreg_ros.core.registration.verify.balanced_fit`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from kentreg_ros.core.scan.clusters import ModelClusters

FloatArray = NDArray[np.float64]


def _log_vmf_constant(kappa: FloatArray) -> FloatArray:
    """``log C(kappa)``, ``C = kappa / (4 pi sinh kappa)``, stable for all kappa >= 0."""
    k = np.maximum(kappa, 1e-12)
    out: FloatArray = np.log(k / (2.0 * np.pi * -np.expm1(-2.0 * k))) - k
    return out


def _align(a: FloatArray, b: FloatArray) -> FloatArray:
    """Rotations (H, 3, 3) taking unit vectors ``a`` (H, 3) onto ``b`` (H, 3) by the shortest arc;
    antiparallel pairs turn by pi about an axis perpendicular to ``a``."""
    v = np.cross(a, b)
    c = np.einsum('ij,ij->i', a, b)
    h = len(a)
    vx = np.zeros((h, 3, 3))
    vx[:, 0, 1], vx[:, 0, 2], vx[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    vx[:, 1, 0], vx[:, 2, 0], vx[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    anti = c < -1.0 + 1e-9
    scale = np.where(anti, 0.0, 1.0 / np.where(anti, 1.0, 1.0 + c))
    R = np.eye(3)[None] + vx + (vx @ vx) * scale[:, None, None]
    if anti.any():
        # Any axis perpendicular to a: cross with the coordinate axis least aligned with it.
        aa = a[anti]
        helper = np.eye(3)[np.argmin(np.abs(aa), axis=1)]
        axis = np.cross(aa, helper)
        axis /= np.linalg.norm(axis, axis=1)[:, None]
        R[anti] = 2.0 * axis[:, :, None] * axis[:, None, :] - np.eye(3)[None]
    return R


def _axis_angle(axes: FloatArray, angles: FloatArray) -> FloatArray:
    """Rodrigues for (H, 3) unit axes and (H,) angles."""
    kx = np.zeros((len(axes), 3, 3))
    kx[:, 0, 1], kx[:, 0, 2], kx[:, 1, 2] = -axes[:, 2], axes[:, 1], -axes[:, 0]
    kx[:, 1, 0], kx[:, 2, 0], kx[:, 2, 1] = axes[:, 2], -axes[:, 1], axes[:, 0]
    s = np.sin(angles)[:, None, None]
    c = (1.0 - np.cos(angles))[:, None, None]
    out: FloatArray = np.eye(3)[None] + s * kx + c * (kx @ kx)
    return out


def twist_hypotheses(source: ModelClusters, target: ModelClusters, step_deg: float) -> FloatArray:
    """Rotations aligning each source cluster mean with each target cluster mean, then turned
    about the target mean in steps of ``step_deg``; shape (K_s * K_t * n_steps, 3, 3)."""
    mu = source.gamma[:, :, 0]
    nu = target.gamma[:, :, 0]
    ks, kt = len(mu), len(nu)
    a = np.repeat(mu, kt, axis=0)
    b = np.tile(nu, (ks, 1))
    base = _align(a, b)  # (ks * kt, 3, 3)
    steps = max(int(round(360.0 / step_deg)), 1)
    angles = np.arange(steps) * (2.0 * np.pi / steps)
    axes = np.repeat(b, steps, axis=0)
    twist = _axis_angle(axes, np.tile(angles, len(b)))
    out: FloatArray = twist @ np.repeat(base, steps, axis=0)
    return out


def mixture_overlap(
    rotations: FloatArray, source: ModelClusters, target: ModelClusters, kappa_cap: float
) -> FloatArray:
    """Log of the overlap integral ``S(R)`` (module docstring) for every rotation, shape (H,)."""
    mu = source.gamma[:, :, 0]
    nu = target.gamma[:, :, 0]
    k_s = np.minimum(source.kappa, kappa_cap)
    k_t = np.minimum(target.kappa, kappa_cap)
    rotated = np.einsum('hab,ib->hia', rotations, mu)  # (H, Ks, 3)
    a = k_s[None, :, None, None] * rotated[:, :, None, :]  # (H, Ks, 1, 3)
    b = (k_t[:, None] * nu)[None, None, :, :]  # (1, 1, Kt, 3)
    norm = np.linalg.norm(a + b, axis=-1)  # (H, Ks, Kt)
    log_terms = (
        np.log(source.weights)[:, None]
        + np.log(target.weights)[None, :]
        + _log_vmf_constant(k_s)[:, None]
        + _log_vmf_constant(k_t)[None, :]
    )[None] - _log_vmf_constant(norm)
    top = log_terms.max(axis=(1, 2))
    out: FloatArray = top + np.log(np.exp(log_terms - top[:, None, None]).sum(axis=(1, 2)))
    return out


def distinct_best(
    rotations: FloatArray, scores: FloatArray, count: int, min_separation_deg: float
) -> list[int]:
    """Indices of up to ``count`` best-scoring rotations, each at least ``min_separation_deg``
    from every better one (greedy non-maximum suppression)."""
    alive = np.isfinite(scores)
    cos_limit = np.cos(np.radians(min_separation_deg))
    chosen: list[int] = []
    while alive.any() and len(chosen) < count:
        best = int(np.flatnonzero(alive)[np.argmax(scores[alive])])
        chosen.append(best)
        # cos of the angle between rotations: (tr(R_best^T R) - 1) / 2.
        cos = (np.einsum('ab,hab->h', rotations[best], rotations) - 1.0) / 2.0
        alive &= cos < cos_limit
    return chosen
