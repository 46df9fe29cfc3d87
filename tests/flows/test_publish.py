"""Names and tags of calibration runs, from the session folder (no server needed)."""

import json

from flows.publish import _identity, _name, run_tags


def test_names_and_tags_say_camera_session_method_and_rig(tmp_path):
    (tmp_path / "wall").mkdir()
    (tmp_path / "wall" / "session.json").write_text(json.dumps({"camera_id": "ixu150-sn0042", "method": "field"}))
    ident = _identity(tmp_path / "wall")
    assert _name(ident["camera_id"], ident["session_id"], ident["method"]) == "calibrate/ixu150-sn0042/wall (field)"
    assert run_tags("ixu150-sn0042", "field") == ["fieldcal", "camera:ixu150-sn0042", "method:field"]
    rig = tmp_path / "2026-11-20-rig"
    rig.mkdir()
    (rig / "session.json").write_text(json.dumps({"rig": {"rig_id": "oblique5-sn0003"}, "method": "field",
                                                  "session_id": "2026-11-20-a"}))
    ident = _identity(rig)
    assert (ident["camera_id"], ident["session_id"], ident["rig_id"]) == ("oblique5-sn0003", "2026-11-20-a",
                                                                          "oblique5-sn0003")
    assert run_tags("oblique5-sn0003", "field", "oblique5-sn0003")[-1] == "rig:oblique5-sn0003"
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "session.json").write_text("{not json")
    assert _name(**{k: v for k, v in _identity(tmp_path / "bad").items() if k != "rig_id"}) == "calibrate/?/bad"
