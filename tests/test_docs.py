"""docs/methods.md names real functions: every dotted ``fieldcal.`` name it cites resolves."""

import importlib
import re
from pathlib import Path

import pytest

DOC = Path(__file__).resolve().parents[1] / "docs" / "methods.md"
NAMES = sorted(set(re.findall(r"`(fieldcal(?:\.\w+)+)", DOC.read_text())))


def _resolve(dotted: str):
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except ModuleNotFoundError:
            continue
        for attr in parts[cut:]:
            obj = getattr(obj, attr)
        return obj
    raise ModuleNotFoundError(dotted)


def test_methods_page_cites_names():
    assert len(NAMES) > 30


@pytest.mark.parametrize("dotted", NAMES)
def test_each_cited_name_exists(dotted):
    assert _resolve(dotted) is not None
