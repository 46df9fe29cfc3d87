"""Planar calibration boards: how a field is recognised as one, and its low-order warp.

A **planar board** (a printed chessboard, a machined disc plate) is given by the nominal
coordinates of its points, which lie in one plane exactly; a surveyed field, flat or not,
never does (a survey scatters by its sigma in all three coordinates). So a field is a
planar board when every surveyed target it observes lies within
:data:`BOARD_FLATNESS_M` (1 um) of the best-fit plane of those targets, there are at
least :data:`MIN_BOARD_TARGETS` of them and they are not collinear
(:func:`is_planar_board`). A real board is not flat to that: paper on glass or an
aluminium plate bows by tens of microns, which at a board's scale moves f by several of
its sigmas (bench/README_uncertainty.md, "Planar boards").

Board models (``AdjustmentOptions.board_model``, ``session.json`` ``field.board_model``;
docs/uncertainty.md section 2c):

``"warp"`` (the default for a planar board)
    The targets are held at their nominal coordinates displaced along the board's normal
    ``n`` by a low-order deflection (as mrcal's board model does, but with three terms):

        X_t = X0_t + n * 1e-3 * w(u_t, v_t),
        w(u, v) = c_uu (1 - u^2) + c_vv (1 - v^2) + c_uv u v      [mm]

    with ``u, v`` the target's coordinates along the board's two main axes ``e1, e2``
    (:func:`fieldcal.field.geometry.plane_frame`) scaled to [-1, 1] over the targets'
    extent. ``c_uu``, ``c_vv`` are the bows along ``e1`` and ``e2`` (the deflection of the
    middle relative to the edges), ``c_uv`` the twist (the corners' deflection). Constant
    and tilt terms are left out: they are a motion of the board, which the exterior
    orientations take up. The coefficients are unknowns of the bundle adjustment with
    analytic derivatives (:class:`BoardWarp.basis`; the image residuals' derivative by
    ``c_j`` is their derivative by the target's coordinates times ``n B_j``) and are
    reported with their sigmas.
``"rigid"``
    The nominal coordinates held fixed (``targets_adjusted = False``; OpenCV's and the
    Caltech toolbox's model); their stated sigma is propagated as survey error.
``"points"``
    Every point adjusted, its nominal coordinates entering as observations weighted by
    their sigma, with variance components (the default of a surveyed field).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fieldcal.errors import InputError
from fieldcal.field.geometry import is_collinear, plane_frame

__all__ = ["BOARD_FLATNESS_M", "MIN_BOARD_TARGETS", "BOARD_MODELS", "WARP_PARAMS", "BoardWarp",
           "is_planar_board", "resolve_board_model", "board_warp", "facing"]

BOARD_FLATNESS_M = 1e-6
"""Largest distance [m] of a target from the best-fit plane for the field to count as a
planar board (nominal coordinates: a survey scatters by millimetres)."""
MIN_BOARD_TARGETS = 9
"""A planar board has at least this many observed surveyed targets (a 3 x 3 grid)."""
BOARD_MODELS = ("auto", "warp", "rigid", "points")
"""Values of ``board_model``: ``"auto"`` is ``"warp"`` on a planar board (``"rigid"`` when the
targets are asked to be held fixed) and nothing on any other field."""
WARP_PARAMS = ("warp_uu_mm", "warp_vv_mm", "warp_uv_mm")
"""Names of the warp coefficients ``c_uu, c_vv, c_uv`` [mm] (module docstring)."""


def is_planar_board(xyz_m) -> bool:
    """Whether target coordinates (n, 3) [m] are those of a planar board (module docstring)."""
    X = np.asarray(xyz_m, float)
    X = X[np.isfinite(X).all(axis=1)]
    if len(X) < MIN_BOARD_TARGETS or is_collinear(X):
        return False
    origin, B = plane_frame(X)
    return bool(np.max(np.abs((X - origin) @ B[:, 2])) <= BOARD_FLATNESS_M)


def resolve_board_model(requested: str, planar_board: bool, targets_adjusted: bool) -> str | None:
    """The board model an adjustment uses: ``"warp"``, ``"rigid"``, ``"points"`` or ``None``
    (not a board; ``requested`` must then be ``"auto"``).

    ``"auto"`` on a planar board is ``"warp"``, or ``"rigid"`` when ``targets_adjusted`` is
    False (the user asked for the targets held fixed, e.g. ``--targets-fixed``).
    """
    if requested not in BOARD_MODELS:
        raise InputError(f"board_model must be one of {', '.join(map(repr, BOARD_MODELS))}, got {requested!r}",
                         "adjustment options")
    if not planar_board:
        if requested != "auto":
            raise InputError(f"board_model {requested!r} is for a planar board: the observed surveyed targets "
                             f"are not coplanar to {BOARD_FLATNESS_M * 1e6:g} um (or fewer than "
                             f"{MIN_BOARD_TARGETS})", "adjustment options")
        return None
    if requested == "auto":
        return "warp" if targets_adjusted else "rigid"
    return requested


@dataclass(frozen=True)
class BoardWarp:
    """The warp model of one board (module docstring).

    Attributes
    ----------
    origin_m : (3,) ndarray
        The centre of the targets' extent in the board plane [m].
    axes : (3, 3) ndarray
        Columns ``e1, e2, n``: the board's main axes and its normal (right-handed).
    half_extent_m : (2,) ndarray
        Half the targets' extent along ``e1`` and ``e2`` [m] (``u, v`` = +-1 at the edges).
    """

    origin_m: np.ndarray
    axes: np.ndarray
    half_extent_m: np.ndarray

    names = WARP_PARAMS

    @property
    def normal(self) -> np.ndarray:
        return self.axes[:, 2]

    def uv(self, xyz_m):
        """Normalised board coordinates (n, 2) of points (n, 3) [m]."""
        P = (np.asarray(xyz_m, float) - self.origin_m) @ self.axes[:, :2]
        return P / self.half_extent_m

    def basis(self, xyz_m):
        """``B`` (n, 3): the deflections [mm per mm of coefficient] of the three terms at the points."""
        uv = self.uv(xyz_m)
        u, v = uv[:, 0], uv[:, 1]
        return np.stack([1.0 - u * u, 1.0 - v * v, u * v], axis=1)

    def deflection_mm(self, coeffs_mm, xyz_m):
        """``w`` (n,) [mm] at the points for coefficients (3,) [mm]."""
        return self.basis(xyz_m) @ np.asarray(coeffs_mm, float)

    def displaced(self, coeffs_mm, xyz_m):
        """The points (n, 3) [m] moved along the normal by the deflection."""
        return np.asarray(xyz_m, float) + 1e-3 * self.deflection_mm(coeffs_mm, xyz_m)[:, None] * self.normal

    def to_dict(self) -> dict:
        return {"origin_m": self.origin_m.tolist(), "e1": self.axes[:, 0].tolist(), "e2": self.axes[:, 1].tolist(),
                "normal": self.normal.tolist(), "half_extent_mm": (1000.0 * self.half_extent_m).tolist()}


def board_warp(xyz_m) -> BoardWarp:
    """The :class:`BoardWarp` frame of a planar board's targets (n, 3) [m]."""
    X = np.asarray(xyz_m, float)
    X = X[np.isfinite(X).all(axis=1)]
    centroid, B = plane_frame(X)
    P = (X - centroid) @ B[:, :2]
    lo, hi = P.min(axis=0), P.max(axis=0)
    origin = centroid + B[:, :2] @ (0.5 * (lo + hi))
    return BoardWarp(origin, B, np.maximum(0.5 * (hi - lo), 1e-9))


def facing(warp: BoardWarp, center_m) -> BoardWarp:
    """The same warp frame with its normal towards the mean of the camera centres (n, 3) [m]
    (``e2`` flipped with it, the frame stays right-handed), so that a positive deflection
    bows the board towards the cameras."""
    side = float(np.mean((np.asarray(center_m, float) - warp.origin_m) @ warp.normal))
    if side >= 0:
        return warp
    axes = warp.axes * np.array([1.0, -1.0, -1.0])
    return BoardWarp(warp.origin_m, axes, warp.half_extent_m)
