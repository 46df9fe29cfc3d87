"""One session as a batch job, without any workflow engine (fieldcal/batch.py).

What the flows decide is decided here, on a real lake in a temporary folder: which images
are missing, which are cached (by the key of content hash and measuring settings), whether
a run is a no-op, and the batch sizes.
"""

import shutil

import pytest

from fieldcal import batch, pipeline
from fieldcal.lake.store import Lake
from fieldcal.session.fingerprint import sha256_file
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


def test_batches_shrink_towards_the_end_but_never_below_the_overhead():
    # full-size images: 1 s of work, 0.3 s overhead per task; 70 images on 2 workers
    sizes = batch.plan_batches(70, 2, 1.0, 0.3)
    assert sum(sizes) == 70 and sizes == [35, 18, 9, 4, 2, 1, 1]      # half of what is left per worker
    assert sizes == sorted(sizes, reverse=True)
    # two tasks per worker: each takes a quarter of what is left
    assert batch.plan_batches(70, 2, 1.0, 0.3, tasks_per_worker=2)[:4] == [18, 13, 10, 8]
    # 5 ms frames with 0.5 s overhead: no task shorter than its overhead (100 frames) ...
    assert batch.plan_batches(378, 2, 0.005, 0.5) == [189, 100, 89]
    # ... unless a worker would get nothing: then half each
    assert batch.plan_batches(178, 2, 0.005, 0.5) == [89, 89]
    assert batch.plan_batches(3, 2, 0.001, 0.3) == [2, 1]
    # slow images and cheap tasks: the guided sizes alone, at most 60 s of work each
    assert batch.plan_batches(8, 2, 30.0, 0.1) == [2, 2, 2, 1, 1]
    assert batch.plan_batches(8, 2, 10.0, 0.1) == [4, 2, 1, 1]
    # at most 60 s of work per task beyond the floor
    assert max(batch.plan_batches(1000, 2, 1.0, 0.1)) == 60
    assert batch.plan_batches(10, 2, 0.0, 1.0) == [10]            # nothing to measure (cached): one task
    assert batch.plan_batches(0, 2, 1.0, 0.3) == []


def test_before_any_image_is_read_the_costs_come_from_the_files_sizes():
    image_s, overhead_s = batch.prior_costs([103_093_472, 0, 59_000_000])   # 0: unreadable, ignored
    assert image_s == pytest.approx((103_093_472 + 59_000_000) / 2 / batch.PRIOR_BYTES_PER_S)
    assert overhead_s == batch.PRIOR_TASK_OVERHEAD_S
    assert batch.prior_costs([]) == (0.0, batch.PRIOR_TASK_OVERHEAD_S)
    # 72 bench frames on two threads: the guided sizes, one of 36 for each thread's first task
    sizes = batch.plan_batches(72, 2, *batch.prior_costs([103_093_472] * 36 + [79_850_000] * 36))
    assert sizes == [36, 18, 9, 5, 2, 1, 1]


def test_batches_are_placed_by_images_so_each_worker_gets_an_equal_share():
    sizes = batch.plan_batches(70, 2, 1.0, 0.3)
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
