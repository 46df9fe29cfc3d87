"""What bounded systematic errors of image points can do to the camera parameters.

A least-squares estimate moves linearly with its observations: for an error ``dl_k`` [px] of
image point ``k`` the interior parameter ``j`` moves by ``dp_j = sum_k g_jk . dl_k / sigma_k``,
``g_jk`` (2,) the row ``j`` of ``N^-1 J^T`` (whitened). When only a bound ``|dl_k| <= b_k`` is
known (the perspective eccentricity of a disc whose normal is unknown,
:func:`fieldcal.field.normals.eccentricity_bound_px`), the largest move is

    ``dp_j,max = sum_k |g_jk| b_k / sigma_k``        (every error aligned against the estimate)

which :func:`parameter_bounds` computes; :func:`eccentricity_bias_bounds` bounds it tighter for
the eccentricity of discs with unknown normals (one normal per disc, the same in every image),
and :func:`with_bias_bounds` adds a bound in quadrature to the parameters' variances: their
sigma then is at least the largest bias (docs/uncertainty.md section 2: never a sigma the bias
exceeds).

With the targets adjusted (the default), their coordinates are eliminated per target
(Schur complement): with ``D_k`` the whitened derivatives of point ``k`` by the reduced unknowns
``[interior | exterior]``, ``T_k`` by its target's coordinates, ``a_j`` the row ``j`` of the
reduced unit covariance ``S^-1``, ``u_k = D_k a_j`` and, per target,
``N_tt = sum_k T_k^T T_k + I / sigma_survey^2``, ``q_t = sum_k T_k^T u_k``:

    ``g_jk = u_k - T_k N_tt^-1 q_t``.

With the targets fixed ``g_jk = u_k``.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from fieldcal.field.adjustment import FieldResult
from fieldcal.field.bundle import BundleModel

__all__ = ["sensitivities", "parameter_bounds", "eccentricity_bias_bounds", "with_bias_bounds"]


def _final_model(res: FieldResult):
    """The final adjustment's model (its active points and weights) and its solution vector."""
    data, vc = res.data, res.variance_components
    weighted = replace(data, obs=replace(data.obs, sigma_px=np.hypot(data.obs.sigma_px, vc.image_floor_px)),
                       targets=replace(data.targets, sigma_mm=data.targets.sigma_mm * vc.survey_factor))
    model = BundleModel(weighted, res.params, res.estimate, res.R_world_to_camera,
                        targets_adjusted=res.options.targets_adjusted, obs_active=res.obs_used,
                        survey_active=res.survey_used)
    return model, model.pack(res.params, res.center_m, res.targets_m)


def _reduced_normal_matrix(model, jb):
    """``N = J^T J`` over ``[interior | exterior]`` (targets fixed), dense."""
    p = model.n_int
    D = np.concatenate([jb.d_int, jb.d_ext], axis=2)                  # (m, 2, p + 6)
    cols = np.concatenate([np.broadcast_to(np.arange(p), (len(model.img), p)),
                           p + 6 * model.img[:, None] + np.arange(6)], axis=1)
    N = np.zeros((model.n_reduced, model.n_reduced))
    np.add.at(N, (cols[:, :, None], cols[:, None, :]), np.einsum("kca,kcb->kab", D, D))
    return N


def sensitivities(res: FieldResult):
    """``(k, g)``: the observations of ``res.data`` in the final adjustment (indices, (m,)) and
    the move of every interior parameter per pixel of their error, ``dp_j = sum_k g[k, j] .
    dl_k`` ((m, n_int, 2), parameter units per px; module docstring, linear)."""
    model, x = _final_model(res)
    _, jb, _ = model.residuals_and_blocks(x, True)
    p = model.n_int
    if model.targets_adjusted:
        unit = np.asarray(res.covariance, float) / max(res.variance_components.unit_sigma, 1e-300) ** 2
    else:                   # the stored covariance holds the survey's consider term: N^-1 afresh
        unit = np.linalg.inv(_reduced_normal_matrix(model, jb))
    A = unit[:p]                                                    # rows of the interior, (p, n_r)
    a_int, a_ext = A[:, :p], A[:, p:].reshape(p, model.n_images, 6)
    # u (m, p, 2): the whitened points' derivatives along each parameter's covariance row
    u = (np.einsum("kcq,jq->kjc", jb.d_int, a_int)
         + np.einsum("kcq,kjq->kjc", jb.d_ext, a_ext[:, model.img].transpose(1, 0, 2)))
    if model.targets_adjusted:
        T = jb.d_tgt                                                # (m, 2, 3)
        slot = model.tgt_slot
        n_t = len(model.target_index)
        Ntt = np.zeros((n_t, 3, 3))
        np.add.at(Ntt, slot, np.einsum("kca,kcb->kab", T, T))
        s = model.survey_k
        Ntt[model.t_slot[s]] += np.eye(3)[None] / (model.sigma_m[s] ** 2)[:, None, None]
        q = np.zeros((n_t, p, 3))
        np.add.at(q, slot, np.einsum("kca,kjc->kja", T, u))
        w = np.linalg.solve(Ntt[:, None], q[..., None])[..., 0]       # N_tt^-1 q, (n_t, p, 3)
        u = u - np.einsum("kca,kja->kjc", T, w[slot])
    # r = (l - f(x)) / sigma and Gauss-Newton's dx = -(J^T J)^-1 J^T dr with J = dr/dx
    return model.k, -u / model.sigma_px[:, None, None]


def parameter_bounds(res: FieldResult, bound_px) -> np.ndarray:
    """The largest move (n_int,) of every estimated interior parameter (``res.estimate``, its
    units) that errors of the image points within ``bound_px`` ((m,) [px] per observation of
    ``res.data``, 0 for none) can cause (module docstring)."""
    k, g = sensitivities(res)
    return np.einsum("kj,k->j", np.linalg.norm(g, axis=2), np.asarray(bound_px, float)[k])


LATTICE_MARGIN = 1.10
"""A lattice's maximum of a smooth function falls short of the true one (measured on wide_field:
by up to 5 % with 128 directions and 32 rim points, 2.5 % with 400, against the best of 2000
random normals with 256 rim points): the bound is raised by this."""


def eccentricity_bias_bounds(res: FieldResult, unknown, radius_m, *, max_incidence_deg: float = 80.0,
                             directions: int = 128) -> np.ndarray:
    """The largest move (n_int,) of every interior parameter that the perspective eccentricity
    of the discs whose normal is unknown (``unknown``: (m,) bool over ``res.data.obs``) can cause.

    A disc has one normal in every image: per target the move ``s_t(n) = sum_k g_k . e_k(n)``
    over its image points is evaluated for ``directions`` normals (a half-sphere lattice about
    the mean direction to the cameras that see it, within ``max_incidence_deg``; the adjusted
    camera, poses and target coordinates), and the bound is ``sum_t max_n |s_t(n)|`` (every
    target's normal the worst it can be, independently), times :data:`LATTICE_MARGIN`. Tighter
    than :func:`parameter_bounds`
    of the per-image bounds, which lets a disc's error turn freely from image to image.
    """
    from fieldcal.field.eccentricity import correction_px
    from fieldcal.field.normals import hemisphere

    k, g = sensitivities(res)
    sel = np.asarray(unknown, bool)[k]
    k, g = k[sel], g[sel]
    p = len(res.estimate)
    if not len(k):
        return np.zeros(p)
    obs = res.data.obs
    img, tgt = obs.image[k], obs.target[k]
    targets, slot = np.unique(tgt, return_inverse=True)
    X = np.asarray(res.targets_m, float)
    C = np.asarray(res.center_m, float)
    towards = np.zeros((len(targets), 3))
    np.add.at(towards, slot, C[img])
    towards /= np.bincount(slot)[:, None]
    ray = towards - X[targets]
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    ref = np.where((np.abs(ray[:, 0]) > 0.9)[:, None], [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    a = ref - np.sum(ref * ray, axis=1, keepdims=True) * ray
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = np.cross(ray, a)
    H = hemisphere(directions)
    H = H[H[:, 2] >= np.cos(np.radians(max_incidence_deg))]
    N = H[None, :, 0:1] * a[:, None] + H[None, :, 1:2] * b[:, None] + H[None, :, 2:3] * ray[:, None]
    D = len(H)
    s = np.zeros((len(targets), D, p))
    cam = res.camera
    for i in np.unique(img):
        m = np.flatnonzero(img == i)
        e = correction_px(cam, res.R_world_to_camera[i], C[i], np.repeat(X[tgt[m]], D, axis=0),
                          N[slot[m]].reshape(-1, 3), radius_m, rim_points=32).reshape(len(m), D, 2)
        e = np.where(np.isfinite(e), e, 0.0)
        np.add.at(s, slot[m], np.einsum("kjc,kdc->kdj", g[m], e))
    return LATTICE_MARGIN * np.abs(s).max(axis=1).sum(axis=0)


def with_bias_bounds(res: FieldResult, moves) -> tuple[FieldResult, dict]:
    """``res`` with the largest moves ``moves`` ((n_int,), parameter units; e.g. of
    :func:`eccentricity_bias_bounds`) added in quadrature to the interior parameters' variances
    (sigma, covariance diagonal, correlation), and those moves as ``{parameter: move}``."""
    d = np.asarray(moves, float)
    p = len(res.estimate)
    cov = np.array(res.covariance, float)
    cov[np.arange(p), np.arange(p)] += d**2
    s = np.sqrt(np.diag(cov)[:p])
    sigma = dict(res.sigma)
    sigma.update({name: float(s[j]) for j, name in enumerate(res.estimate)})
    corr = cov[:p, :p] / np.outer(s, s)
    moves = {name: float(d[j]) for j, name in enumerate(res.estimate)}
    return replace(res, covariance=cov, sigma=sigma, correlation_interior=corr), moves
