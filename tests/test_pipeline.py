"""The plain steps of a calibration (fieldcal/pipeline.py) on an observations-only session.

Issue 13, goal 5: an image listed with fewer observations than an image needs to be
oriented is reported and left out, exactly as in an image session, and the run goes on
while enough images remain.
"""

import re

import pytest

from fieldcal import pipeline
from fieldcal.errors import GeometryError
from fieldcal.field.adjustment import MIN_POINTS_PER_IMAGE
from fieldcal.synthetic.field import wide_field
from fieldcal.synthetic.session_writer import write_field_session


def _keep_rows(folder, keep) -> None:
    lines = (folder / "observations.csv").read_text().splitlines()
    (folder / "observations.csv").write_text("\n".join([lines[0]] + [ln for ln in lines[1:] if keep(ln)]) + "\n")


def test_images_with_too_few_observations_are_left_out_and_the_run_goes_on(tmp_path):
    folder = tmp_path / "wall"
    write_field_session(folder, wide_field(seed=6), images=False, observations_csv=True, camera_id="cam-few")
    prepared = pipeline.prepare(folder)
    names = [im.file for im in prepared.session.images]
    none, few = names[0], names[1]
    seen = {}

    def keep(line):
        image = line.split(",")[0]
        seen[image] = seen.get(image, 0) + 1
        return image != none and (image != few or seen[image] <= MIN_POINTS_PER_IMAGE - 1)

    _keep_rows(folder, keep)
    prepared = pipeline.prepare(folder)
    outcome = pipeline.solve(prepared, {}, fingerprint_=pipeline.input_fingerprint(prepared, {}))
    left = {item["image"]: item["reason"] for item in outcome.left_out}
    assert left == {none: f"only 0 observed target(s); an image needs at least {MIN_POINTS_PER_IMAGE}",
                    few: f"only {MIN_POINTS_PER_IMAGE - 1} observed target(s); an image needs at least "
                         f"{MIN_POINTS_PER_IMAGE}"}
    doc = outcome.document
    assert doc["stats"]["n_images"] == len(names) - 2 and doc["stats"]["left_out_images"] == [none, few]
    assert {im["file"] for im in doc["images"]} == set(names) - {none, few}


def test_the_run_stops_when_too_few_images_remain(tmp_path):
    folder = tmp_path / "wall"
    write_field_session(folder, wide_field(seed=7), images=False, observations_csv=True, camera_id="cam-few")
    two = [im.file for im in pipeline.prepare(folder).session.images][:2]
    _keep_rows(folder, lambda line: line.split(",")[0] in two)
    prepared = pipeline.prepare(folder)
    names = [im.file for im in prepared.session.images]
    first = next(n for n in names if n not in two)
    with pytest.raises(GeometryError, match=rf"^{re.escape(first)}: only 0 observed target\(s\); an image needs at "
                       rf"least {MIN_POINTS_PER_IMAGE} \(and {len(names) - 3} more image\(s\) left out\); 2 "
                       r"image\(s\) remain, the field method needs at least 3$"):
        pipeline.solve(prepared, {}, fingerprint_=pipeline.input_fingerprint(prepared, {}))
