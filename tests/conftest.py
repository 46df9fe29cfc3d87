"""Shared fixtures: the S3-compatible server (moto), Prefect's local server and a Dask cluster.

Each is started once per test session, when a test first asks for it.

Hypothesis runs derandomised (the profile ``ci``, the default): the same commit draws the
same examples on every machine, so a verdict never depends on chance. To search further
(new examples every run, many more of them), run with ``HYPOTHESIS_PROFILE=explore``.

Two tiers: ``make test`` runs everything, on two pytest-xdist workers (one test file per
worker at a time, so module fixtures are made once; the longest files first, :data:`FIRST`).
``make check`` (daily work, under 2 minutes of CPU here) leaves out the tests marked
``slow`` (end-to-end runs of flows and servers) and ``heavy``: the tests listed in
:data:`HEAVY`, chosen with ``pytest --durations=0 -m "not slow"`` as the ones that take most
of the rest (the paper-sized adjustments and their Monte Carlo, real photographs, rendered
image sessions and reports, the S3 server, concurrent commits, subprocesses).
"""

import os

import pytest
from hypothesis import settings

from tests.conftest_prefect import dask_cluster, prefect_server  # noqa: F401
from tests.conftest_s3 import s3_lake, s3_server  # noqa: F401

settings.register_profile("ci", derandomize=True, database=None, deadline=None, print_blob=True)
settings.register_profile("explore", derandomize=False, database=None, deadline=None, max_examples=5000,
                          print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))
# a run writes its certificate (and with "all" its report: plots, 2-9 s) into the lake; the
# tests of that (tests/flows/test_prefect_native.py) turn it on, the other runs skip it
os.environ.setdefault("FIELDCAL_REPORTS", "off")

HEAVY = (
    "tests/field/test_adjustment.py::test_monte_carlo_sigmas_are_honest",
    "tests/field/test_adjustment.py::test_lmqn_lm_and_scipy_reach_the_same_optimum",
    "tests/field/test_adjustment.py::test_paper_geometry_recovers_the_camera",
    "tests/field/test_adjustment.py::test_paper_correction_field_is_as_good_as_its_covariance_says",
    "tests/field/test_adjustment.py::test_fixed_targets_give_the_survey_noise_regime",
    "tests/field/test_adjustment.py::test_one_percent_blunders_are_all_rejected_and_the_result_still_passes",
    "tests/field/test_adjustment.py::test_blunders_with_fixed_targets_reject_the_images_of_moved_targets",
    "tests/field/test_adjustment.py::test_lmqn_and_lm_reach_the_same_optimum_on_the_paper_problem",
    "tests/field/test_adjustment.py::test_wide_angle_camera_and_its_correction_field",
    "tests/field/test_adjustment.py::test_dbat_sheet_agrees_with_opencv_on_the_same_points",
    "tests/field/test_dbat_photos.py",
    "tests/field/test_from_images.py",
    "tests/measure/test_coded.py::test_ids_and_centres",
    "tests/measure/test_coded.py::test_downscaled_detection_agrees_with_full_resolution",
    "tests/lake/test_lake.py::test_concurrent_commits_of_",
    "tests/lake/test_lake_s3.py",
    "tests/measure/test_bad_images.py",
    "tests/products/test_report.py",
    "tests/goniometer/test_goniometer.py::test_measure_frame_reports_bad_files_instead_of_raising",
    "tests/session/test_fuzz.py::test_the_strategies_never_use_the_random_module",
    "tests/flows/test_cli_reports.py",
    "tests/test_realdata.py",
)
"""Node-id prefixes of the tests ``make check`` leaves out (besides ``slow``)."""


def pytest_configure(config):
    config.addinivalue_line("markers", "heavy: a test ``make check`` leaves out (tests/conftest.py HEAVY)")


FIRST = (
    "tests/flows/test_readme.py",
    "tests/flows/test_readme_demo.py",
    "tests/flows/test_schedule.py",
    "tests/flows/test_flows_dask.py",
    "tests/flows/test_faults.py",
    "tests/flows/test_flows_s3.py",
    "tests/flows/test_flows.py",
    "tests/field/test_honest_uncertainty.py",
    "tests/field/test_honest_uncertainty_images.py",
    "tests/flows/test_fleet.py",
    "tests/flows/test_server.py",
)
"""Test files that take longest (``--durations``), run first: ``make test`` spreads files over
two pytest-xdist workers in collection order, and a long file started last would leave one
worker idle while the other finishes it."""


def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.nodeid.startswith(HEAVY):
            item.add_marker(pytest.mark.heavy)
    rank = {name: k for k, name in enumerate(FIRST)}
    items.sort(key=lambda item: rank.get(item.nodeid.split("::", 1)[0], len(FIRST)))   # stable
