"""Planar boards (issue 23, goal 3): how a field is recognised as a board, the board-warp model's
derivatives, and the default board model against the rendered truth of flat and warped boards.

The scene is :func:`fieldcal.synthetic.field.board_field` (Bouguet's 13 x 12 corner chessboard,
a 640 x 480 camera, 20 poses, 0.1 px image noise): exact image points of the true (flat or
warped) corners plus seeded noise; the session's targets are the board's nominal flat grid.
"""

import json

import numpy as np
import pytest

from fieldcal import pipeline
from fieldcal.analysis.uncertainty import Calibration
from fieldcal.errors import InputError
from fieldcal.field import bundle_kernel
from fieldcal.field.adjustment import AdjustmentOptions, adjust_field
from fieldcal.field.board import BOARD_FLATNESS_M, board_warp, is_planar_board, resolve_board_model
from fieldcal.field.bundle import BundleModel
from fieldcal.model.camera import FIELD_PARAMS, INDEX
from fieldcal.model.rotations import R_from_rotvec
from fieldcal.products import certificate_sections, report
from fieldcal.products.content import board_text
from fieldcal.synthetic.field import board_deflection_mm, board_field, wide_field
from fieldcal.synthetic.session_writer import write_field_session

CORE = ("f_mm", "xp_mm", "yp_mm")


def _z(sf, res):
    return np.array([(res.params[INDEX[p]] - sf.camera.params[INDEX[p]]) / res.sigma[p] for p in CORE])


# ---------------------------------------------------------------------------- what a board is
def test_a_board_is_exactly_planar_nominal_coordinates_and_a_survey_is_not():
    board = board_field(seed=0).data.targets.xyz_m
    assert is_planar_board(board)
    R = R_from_rotvec(np.array([0.3, -0.2, 1.1]))
    assert is_planar_board(board @ R.T + [500123.0, 4.2e6, 310.0])     # a tilted board in UTM: still one
    rng = np.random.default_rng(0)
    bumped = board.copy()
    bumped[7, 2] += 3 * BOARD_FLATNESS_M                                 # one corner 3 um off the plane
    assert not is_planar_board(bumped)
    flat_wall = wide_field(seed=0, relief=False).data.targets.xyz_m      # a flat wall, surveyed to 5 mm
    assert not is_planar_board(flat_wall)
    assert not is_planar_board(wide_field(seed=0).data.targets.xyz_m)   # a 3-D field
    assert not is_planar_board(board[:8])                                # fewer than 9 targets
    line = np.zeros((20, 3))
    line[:, 0] = rng.uniform(0, 1, 20)
    assert not is_planar_board(line)                                     # collinear


def test_board_model_resolution_and_refusals():
    assert resolve_board_model("auto", True, True) == "warp"
    assert resolve_board_model("auto", True, False) == "rigid"           # --targets-fixed on a board
    assert resolve_board_model("points", True, True) == "points"
    assert resolve_board_model("auto", False, True) is None
    with pytest.raises(InputError, match="board_model 'warp' is for a planar board"):
        resolve_board_model("warp", False, True)
    with pytest.raises(InputError, match="board_model must be one of"):
        adjust_field(board_field(seed=0).data, AdjustmentOptions(board_model="bent"))
    with pytest.raises(InputError, match="is for a planar board"):
        adjust_field(wide_field(seed=0).data, AdjustmentOptions(board_model="warp"))
    with pytest.raises(InputError, match="holds the targets fixed: a free network"):
        adjust_field(board_field(seed=0).data, AdjustmentOptions(datum="free", board_model="warp"))
    free = adjust_field(board_field(seed=0).data, AdjustmentOptions(datum="free"))
    assert free.board["model"] == "points" and free.stats()["datum"]["type"] == "free network"
    res = adjust_field(wide_field(seed=0).data)                          # a 3-D field: no board model
    assert "board" not in res.stats() and res.options.targets_adjusted


# ---------------------------------------------------------------------------- derivatives
@pytest.mark.parametrize("implementation", ["numpy", "numba"])
def test_warp_columns_match_central_differences(implementation):
    if implementation == "numba" and bundle_kernel.kernel() is None:
        pytest.skip(bundle_kernel.status())
    sf = board_field(seed=1, shape="dome", amplitude_mm=0.3)
    warp = board_warp(sf.data.targets.xyz_m)
    m = BundleModel(sf.data, sf.camera.params, FIELD_PARAMS, sf.R_world_to_camera, targets_adjusted=False,
                    warp=warp)
    assert m.n_int == len(FIELD_PARAMS) + 3 and m.column_names()[m.n_cam:m.n_int] == list(warp.names)
    x = m.pack(sf.camera.params, sf.center_m, warp_mm=[0.02, -0.05, 0.03])
    r, jb, _ = m.residuals_and_blocks(x, True, implementation=implementation)
    for j in range(m.n_cam, m.n_int):
        e = np.zeros_like(x)
        e[j] = 1e-3                                                      # 1 um of a coefficient [mm]
        num = (m.residuals_and_blocks(x + e, False, implementation=implementation)[0]
               - m.residuals_and_blocks(x - e, False, implementation=implementation)[0]) / 2e-3
        ana = jb.d_int[:, :, j].ravel()
        assert np.abs(num - ana).max() <= 1e-6 * np.abs(num).max(), m.column_names()[j]
    # the camera's columns are those of the model without a warp at the displaced targets
    plain = BundleModel(sf.data, sf.camera.params, FIELD_PARAMS, sf.R_world_to_camera, targets_adjusted=False)
    plain.X_base = m.unpack(x)[3]
    r0, jb0, _ = plain.residuals_and_blocks(plain.pack(sf.camera.params, sf.center_m), True,
                                            implementation=implementation)
    assert np.allclose(r, r0, rtol=0, atol=1e-9)
    assert np.allclose(jb.d_int[:, :, :m.n_cam], jb0.d_int, rtol=1e-12, atol=1e-12)


# ---------------------------------------------------------------------------- against truth
def test_a_domed_board_is_fitted_with_its_shape_and_an_unbiased_camera():
    amp = 0.15                                                           # 150 um: the middle above the corners
    sf = board_field(seed=3, shape="dome", amplitude_mm=amp)
    res = adjust_field(sf.data)                                          # the default: a planar board -> warp
    b = res.stats()["board"]
    assert b["model"] == "warp" and not res.options.targets_adjusted
    assert res.options.board_model == "warp"            # recorded as resolved: a re-adjustment keeps the warp
    truth = {"warp_uu_mm": amp / 2, "warp_vv_mm": amp / 2, "warp_uv_mm": 0.0}
    for name, value in truth.items():
        # 2.5 sigma: a two-sided 1.2 % chance per coefficient for an honest sigma
        assert abs(b["coefficients_mm"][name] - value) <= 2.5 * b["sigma_mm"][name], name
    assert b["coefficients_mm"]["warp_uu_mm"] > 3 * b["sigma_mm"]["warp_uu_mm"]        # the dome is seen
    assert np.all(np.abs(_z(sf, res)) <= 2.5), _z(sf, res)
    # the rigid board (the Caltech toolbox's and OpenCV's model) is biased: its f error grows with
    # the dome (bench/README_uncertainty.md: mean -1.3 sigma at 80 um, -8 sigma at 500 um)
    rigid = adjust_field(sf.data, AdjustmentOptions(board_model="rigid"))
    z_rigid = _z(sf, rigid)[0]
    assert z_rigid < -2.0 and abs(z_rigid) > 2 * abs(_z(sf, res)[0]), (z_rigid, _z(sf, res))
    assert "coefficients_mm" not in rigid.stats()["board"]


@pytest.mark.parametrize("shape", ["flat", "fold"])
def test_flat_and_folded_boards_give_f_xp_yp_within_their_sigmas(shape):
    sf = board_field(seed=4, shape=shape, amplitude_mm=0.08)
    res = adjust_field(sf.data)
    assert res.stats()["board"]["model"] == "warp"
    assert np.all(np.abs(_z(sf, res)) <= 2.5), _z(sf, res)               # 2.5 sigma: 1.2 % two-sided
    if shape == "flat":
        # on a flat board the warp changes nothing beyond noise: within a sigma of the rigid board's
        rigid = adjust_field(sf.data, AdjustmentOptions(board_model="rigid"))
        for p in CORE:
            assert abs(res.params[INDEX[p]] - rigid.params[INDEX[p]]) <= rigid.sigma[p], p
        c, s = res.board["coefficients_mm"], res.board["sigma_mm"]
        assert all(abs(c[n]) <= 2.5 * s[n] for n in c), (c, s)


def test_board_deflection_shapes():
    u = np.array([-1.0, 0.0, 1.0, 0.0])
    v = np.array([-1.0, 0.0, 1.0, 1.0])
    assert np.allclose(board_deflection_mm("dome", 0.1, u, v), [0.0, 0.1, 0.0, 0.05])
    assert np.allclose(board_deflection_mm("fold", 0.1, u, v), [0.0, 0.1, 0.0, 0.1])
    assert np.allclose(board_deflection_mm("flat", 0.1, u, v), 0.0)


# ---------------------------------------------------------------------------- the session and document
def test_a_board_session_records_its_model_and_shape_in_the_document(tmp_path):
    sf = board_field(seed=5, shape="dome", amplitude_mm=0.15)
    folder = tmp_path / "board"
    write_field_session(folder, sf, images=False, observations_csv=True, coded=False, camera_id="cam-board")
    prepared = pipeline.prepare(folder)
    outcome = pipeline.solve(prepared, {}, fingerprint_=pipeline.input_fingerprint(prepared, {}))
    doc = outcome.document
    b = doc["stats"]["board"]
    assert b["model"] == "warp" and doc["stats"]["targets_adjusted"] is False
    assert set(b["coefficients_mm"]) == {"warp_uu_mm", "warp_vv_mm", "warp_uv_mm"}
    text = board_text(Calibration.from_document(doc))                 # the report's and certificate's line
    assert text.startswith("planar board, board model 'warp'") and "twist" in text and "µm" in text
    assert text in report.inputs_summary(Calibration.from_document(doc), outcome.residuals)["went_in"]
    html = certificate_sections._adjustment(Calibration.from_document(doc), outcome.residuals)
    assert any('id="board"' in part and "Planar board, board model" in part for part in html)
    # the session's own choice (session.json field.board_model) is honoured
    manifest = json.loads((folder / "session.json").read_text())
    manifest["field"]["board_model"] = "rigid"
    (folder / "session.json").write_text(json.dumps(manifest))
    prepared = pipeline.prepare(folder)
    doc = pipeline.solve(prepared, {}, fingerprint_=pipeline.input_fingerprint(prepared, {})).document
    assert doc["stats"]["board"] == {"model": "rigid", "planar_board": True}
    manifest["field"]["board_model"] = "bent"
    (folder / "session.json").write_text(json.dumps(manifest))
    with pytest.raises(InputError, match="board_model"):
        pipeline.prepare(folder)
