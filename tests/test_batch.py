"""One session as a batch job, without any workflow engine (fieldcal/batch.py).

What the flows decide is decided here, on a real lake in a temporary folder: which images
are missing, which are cached (by the key of content hash and measuring settings), whether
a run is a no-op, and the batch sizes.
"""

import shutil

import pytest

from fieldcal import batch, pipeline
from fieldcal.contract.fingerprint import sha256_file
from fieldcal.lake.store import Lake
from fieldcal.synthetic.field import wide_field
from fieldcal.synthetic.goniometer import write_session
from fieldcal.synthetic.session_writer import write_field_session


@pytest.fixture(scope="module")
def gonio(tmp_path_factory):
    folder = tmp_path_factory.mktemp("batch") / "lab"
    write_session(folder, "canon5d2", seed=4, raster_scale=0.25, frames_per_angle=1, camera_id="cam-batch")
    return folder


def test_a_plan_finds_missing_images_and_measures_the_rest_once(gonio, tmp_path):
    folder = tmp_path / "lab"
    shutil.copytree(gonio, folder)
    prepared = pipeline.prepare(folder)
    gone = prepared.to_measure[3]
    (folder / gone).unlink()
    lake = Lake(tmp_path / "lake")
    plan = batch.plan_session(prepared, lake)
    assert plan.missing == {gone: "file not found"} and plan.hashes == {gone: batch.MISSING}
    assert plan.cached == {} and plan.todo == [n for n in prepared.to_measure if n != gone]
    assert plan.fingerprint is None and plan.unchanged is None         # hashes unknown: no no-op check

    name = plan.todo[0]
    row = batch.measure_into_lake(prepared, name, lake)
    assert row["status"] == "measured" and row["sha256"] == sha256_file(folder / name) and row["n_rows"] == 1
    assert row["key"] == batch.measurement_key(row["sha256"], batch.measure_settings(prepared))
    again = batch.measure_into_lake(prepared, name, lake, row["sha256"])
    assert again["status"] == "cached" and again["key"] == row["key"] and again["hash_s"] == 0.0
    # a known hash finds the cached observations without reading the image
    plan = batch.plan_session(prepared, lake, {name: row["sha256"]})
    assert plan.cached == {name: row["key"]} and name not in plan.todo
    (table,) = batch.read_observations(prepared, lake, plan.cached).values()
    assert not set(batch.META_KEYS) & set(table.schema.metadata or {})


def test_the_key_changes_with_the_measuring_settings_not_with_the_solver_settings(gonio):
    a = pipeline.prepare(gonio)
    b = pipeline.prepare(gonio, pipeline.Settings(rigorous_goniometer=True))
    assert batch.measure_settings(a) == batch.measure_settings(b)
    key = batch.measurement_key("0" * 64, batch.measure_settings(a))
    other = dict(batch.measure_settings(a), sensor={**batch.measure_settings(a)["sensor"], "pixel_size_um": 6.0})
    assert batch.measurement_key("0" * 64, other) != key and batch.measurement_key("1" * 64, other) != key


def test_the_no_op_check_finds_the_committed_version_of_the_same_inputs(tmp_path):
    folder = tmp_path / "wall"
    write_field_session(folder, wide_field(seed=5), images=False, observations_csv=True, camera_id="cam-noop")
    prepared = pipeline.prepare(folder)
    lake = Lake(tmp_path / "lake")
    plan = batch.plan_session(prepared, lake)
    assert plan.todo == [] and plan.unchanged is None and plan.fingerprint is not None   # nothing to measure
    outcome = pipeline.solve(prepared, {}, fingerprint_=plan.fingerprint)
    version = lake.commit(outcome.document, outcome.arrays, outcome.residuals, array_attrs=outcome.array_attrs)
    assert batch.plan_session(prepared, lake, find_cached=False).unchanged == version
    assert batch.plan_session(prepared, lake, force=True).unchanged is None
    other = pipeline.prepare(folder, pipeline.Settings(targets_adjusted=False))
    assert batch.plan_session(other, lake).unchanged is None             # other settings, other fingerprint


def test_images_are_pulled_one_full_frame_or_a_quarter_second_of_small_frames_at_a_time():
    names = [f"images/{k:03d}.tif" for k in range(72)]
    # before any image is read, the work comes from the files' sizes (0: unreadable, left out)
    image_s = batch.image_seconds([103_093_472, 0, 59_000_000])
    assert image_s == pytest.approx(batch.PRIOR_IMAGE_S + (103_093_472 + 59_000_000) / 2 / batch.PRIOR_BYTES_PER_S)
    assert batch.image_seconds([]) == 0.0
    # full-size frames (~0.3 s each): one per pull, in order
    chunks = batch.pull_chunks(names, batch.image_seconds([103_093_472] * 36 + [79_850_000] * 36))
    assert chunks == [[n] for n in names]
    # a goniometer's 5 ms frames: 50 per pull (0.25 s of work), the rest in the last piece
    chunks = batch.pull_chunks(names * 3, 0.005)
    assert [len(c) for c in chunks] == [50, 50, 50, 50, 16] and sum(chunks, []) == names * 3
    # tiny files still cost their fixed part: 63 per pull, not all in one piece
    assert len(batch.pull_chunks(names * 3, batch.image_seconds([5_500] * 216))[0]) == 63
    assert batch.pull_chunks(names, 0.0) == [names]           # nothing known to cost: one piece
    # several tasks on one queue: each gets pieces even when the estimate is low (12 small
    # field frames, ~0.15 s each, estimated at 0.023 s: one piece, one task for 2 workers)
    twelve = names[:12]
    small = batch.image_seconds([5_600_000] * 12)
    assert batch.pull_chunks(twelve, small) == [twelve]
    assert [len(c) for c in batch.pull_chunks(twelve, small, n_tasks=2)] == [2] * 6
    assert [len(c) for c in batch.pull_chunks(names * 3, 0.005, n_tasks=2)] == [27] * 8
    assert batch.pull_chunks(names, 0.3, n_tasks=2) == [[n] for n in names]
    assert batch.pull_chunks(twelve[:1], 0.0, n_tasks=8) == [twelve[:1]]
    assert batch.pull_chunks([], 0.3) == []


def test_batches_are_placed_by_images_so_each_worker_gets_an_equal_share():
    sizes = [35, 18, 9, 4, 2, 1, 1]
    slots = batch.assign_batches(sizes, 2)
    per_slot = [sum(n for n, k in zip(sizes, slots, strict=True) if k == s) for s in (0, 1)]
    assert slots == [0, 1, 1, 1, 1, 1, 1] and per_slot == [35, 35]
    # by count of tasks, the scheduler's view (alternating), the same sequence would be 47
    # against 23: placed by images, neither slot gets more than half
    by_count = [sum(sizes[0::2]), sum(sizes[1::2])]
    assert by_count == [47, 23]
    assert slots != [k % 2 for k in range(len(sizes))] and max(per_slot) < max(by_count)
    # four slots; a tie goes to the first; one slot: everything on it
    assert batch.assign_batches([5, 5, 5, 5, 3, 2], 4) == [0, 1, 2, 3, 0, 1]
    assert batch.assign_batches([3, 2, 1], 1) == [0, 0, 0]
    assert batch.assign_batches([], 2) == []


def _appends(lake: Lake) -> list[dict]:
    """The observations tables' append commits (the first commit creates the table)."""
    return [c for c in lake.tables.log("observations_goniometer") if c.get("action") == "observations"]


def test_a_batch_of_images_is_one_lake_append_read_back_like_single_ones(gonio, tmp_path):
    prepared = pipeline.prepare(gonio)
    names = prepared.to_measure[:4]
    lake = Lake(tmp_path / "lake")
    rows = batch.measure_many_into_lake(prepared, names, lake, present=set())
    assert [r["status"] for r in rows] == ["measured"] * 4 and [r["image"] for r in rows] == names
    assert len(_appends(lake)) == 1 and _appends(lake)[0]["image"] == "4 images"
    single = Lake(tmp_path / "single")
    for name in names:
        batch.measure_into_lake(prepared, name, single)
    assert len(_appends(single)) == 4
    keys = {r["image"]: r["key"] for r in rows}
    assert batch.read_observations(prepared, Lake(tmp_path / "lake"), keys) == \
        batch.read_observations(prepared, Lake(tmp_path / "single"), keys)
    # with the probe (a retried task), images written before are found and not measured again
    again = batch.measure_many_into_lake(prepared, names, lake, {r["image"]: r["sha256"] for r in rows})
    assert [r["status"] for r in again] == ["cached"] * 4 and len(_appends(lake)) == 1


def test_images_pulled_one_by_one_are_appended_after_every_so_much_measuring(gonio, tmp_path):
    prepared = pipeline.prepare(gonio)
    names = prepared.to_measure[:5]
    lake, done = Lake(tmp_path / "lake"), []

    def pulled():                                        # as a task pulls them from its queue
        yield from names

    rows = batch.measure_many_into_lake(prepared, pulled(), lake, present=set(), on_image=done.append,
                                        append_every_s=0.0)
    assert [r["image"] for r in rows] == names and done == rows
    assert len(_appends(lake)) == 5                      # 0 s: an append after every image
    rows = batch.measure_many_into_lake(prepared, names, Lake(tmp_path / "once"), present=set(),
                                        append_every_s=3600.0)
    assert len(_appends(Lake(tmp_path / "once"))) == 1   # never that much: one append at the end
    assert all(r["write_s"] > 0 for r in rows)


def test_what_a_failing_batch_measured_before_the_failure_is_kept(gonio, tmp_path, monkeypatch):
    prepared = pipeline.prepare(gonio)
    names = prepared.to_measure[:4]
    real, calls = pipeline.measure, []

    def measure_then_fail(prep, name, source=None):
        calls.append(name)
        if len(calls) == 3:
            raise MemoryError("worker out of memory")
        return real(prep, name, source)

    monkeypatch.setattr(pipeline, "measure", measure_then_fail)
    lake = Lake(tmp_path / "lake")
    with pytest.raises(MemoryError):
        batch.measure_many_into_lake(prepared, names, lake, present=set())
    monkeypatch.setattr(pipeline, "measure", real)
    plan = batch.plan_session(prepared, lake, {n: sha256_file(gonio / n) for n in names})
    assert set(plan.cached) == set(names[:2]) and len(_appends(lake)) == 1


def test_images_hashed_by_the_task_are_found_cached_in_the_plans_view_without_lake_probes(gonio, tmp_path):
    prepared = pipeline.prepare(gonio)
    names = prepared.to_measure[:3]
    lake = Lake(tmp_path / "lake")
    batch.measure_many_into_lake(prepared, names[:2], lake, present=set())
    plan = batch.plan_session(prepared, lake)            # no hash known: nothing cached by name yet
    assert plan.cached == {} and len(plan.present) == 2 and names[0] in plan.todo

    def no_probe(*args):
        raise AssertionError("the lake was probed per image")

    lake.has_observations = no_probe
    rows = batch.measure_many_into_lake(prepared, names, lake, present=plan.present)
    assert [r["status"] for r in rows] == ["cached", "cached", "measured"]
