"""Rig sessions (CONTRACT section 3, "Rig sessions"): the manifest is parsed and validated,
bad input refused in one line naming the file and the field."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fieldcal.errors import InputError
from fieldcal.rig import load_rig_session, rig_data_from_observations
from fieldcal.session.loader import load_session
from fieldcal.synthetic.rig import two_head_rig, write_rig_session


@pytest.fixture(scope="module")
def rig_folder(tmp_path_factory):
    return write_rig_session(tmp_path_factory.mktemp("rig") / "bar2-s1", two_head_rig(seed=1))


def _edited(tmp_path, src, edit):
    dst = tmp_path / "s"
    dst.mkdir()
    for name in ("targets.csv", "observations.csv"):
        (dst / name).write_bytes((src / name).read_bytes())
    m = json.loads((src / "session.json").read_text())
    edit(m)
    (dst / "session.json").write_text(json.dumps(m))
    return dst


def test_a_rig_session_is_read_with_its_heads_exposures_and_observations(rig_folder):
    sr = two_head_rig(seed=1)
    sess = load_rig_session(rig_folder)
    assert sess.rig_id == "bar2" and [h.camera_id for h in sess.heads] == ["bar2-left", "bar2-right"]
    assert sess.reference == 0 and len(sess.exposures) == 24 and len(sess.images) == 48
    assert sess.heads[1].sensor == sr.cameras[1].sensor and sess.heads[1].nominal_focal_mm == 20.0
    data = rig_data_from_observations(sess)
    for h in range(2):
        a, b = data.head_data[h], sr.data.head_data[h]
        assert [im.file for im in a.images] == [im.file for im in b.images]
        np.testing.assert_array_equal(data.image_exposure[h], sr.data.image_exposure[h])
        np.testing.assert_allclose(a.obs.uv_px, b.obs.uv_px, atol=1e-6)   # 6 decimals in the file
        np.testing.assert_array_equal(a.obs.target, b.obs.target)


def test_the_single_camera_loader_points_to_the_rig_loader(rig_folder):
    with pytest.raises(InputError, match="a rig session"):
        load_session(rig_folder)


@pytest.mark.parametrize("edit, message", [
    (lambda m: m["rig"].update(reference="nope"), r"reference 'nope' is not one of the rig's cameras"),
    (lambda m: m["rig"]["cameras"].append(dict(m["rig"]["cameras"][0])), r"listed twice in the rig"),
    (lambda m: m["images"][0].update(camera="bar2-middle"), r"names camera 'bar2-middle'.*at /images/0/camera"),
    (lambda m: m["images"][1].update(exposure=m["images"][0]["exposure"]), r"two images of exposure"),
    (lambda m: m["images"][0].pop("exposure"), r"'exposure' is a required property \(at /images/0\)"),
    (lambda m: m.update(camera_id="cam"), r"at /camera_id"),
    (lambda m: m["rig"]["cameras"][1].pop("sensor"), r"'sensor' is a required property \(at /rig/cameras/1\)"),
    (lambda m: m["rig"]["cameras"].pop(1), r"at /rig/cameras"),
    (lambda m: m.update(images=[i for i in m["images"] if i["camera"] != "bar2-right"]),
     r"camera 'bar2-right' of the rig has no image"),
    (lambda m: m.update(estimate=["f_mm", "b1"]), r"at /estimate"),
])
def test_bad_rig_manifests_are_refused_naming_the_file_and_field(tmp_path, rig_folder, edit, message):
    folder = _edited(tmp_path, rig_folder, edit)
    with pytest.raises(InputError, match=message) as err:
        load_rig_session(folder)
    assert str(err.value).startswith(str(folder / "session.json")) and "\n" not in str(err.value)


def test_a_point_off_its_heads_sensor_is_refused(tmp_path, rig_folder):
    folder = _edited(tmp_path, rig_folder, lambda m: None)
    lines = (folder / "observations.csv").read_text().splitlines()
    right = next(i for i, ln in enumerate(lines) if "_right" in ln)
    parts = lines[right].split(",")
    parts[2] = "5500.0"                 # on the left head's 6000 px, not on the right head's 5000 px
    lines[right] = ",".join(parts)
    (folder / "observations.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=r"outside camera 'bar2-right'.s 5000 x 3500 px image"):
        rig_data_from_observations(load_rig_session(folder))
