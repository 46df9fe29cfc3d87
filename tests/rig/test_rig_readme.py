"""Every command line of the README's "Camera rigs" section runs as written (in this process:
rig sessions need no Prefect server), its placeholders filled in."""

from __future__ import annotations

import json
import shlex
from pathlib import Path

from flows import cli

ROOT = Path(__file__).resolve().parents[2]


def rig_lines() -> list[str]:
    text = (ROOT / "README.md").read_text()
    start = text.index("\n## Camera rigs\n")
    end = text.index("\n## ", start + 1)
    return [ln.strip() for ln in text[start:end].splitlines() if ln.startswith("    fieldcal ")]


def test_the_rig_section_of_the_readme_runs_as_written(tmp_path, capsys):
    values = {"RIG1": tmp_path / "rig1", "RIG2": tmp_path / "rig2", "LAKE": tmp_path / "lake",
              "RIG.json": tmp_path / "rig.json"}
    versions = []
    lines = rig_lines()
    assert [shlex.split(ln)[1] for ln in lines] == ["synth", "synth", "run", "run", "compare", "history"]
    outputs = {}
    for line in lines:
        values.update(RIG_V1=versions[0] if versions else "", RIG_V2=versions[-1] if versions else "")
        argv = [str(values.get(a, a)) for a in shlex.split(line, comments=True)[1:]]
        status = cli.main(argv)
        out = capsys.readouterr()
        assert status == 0, f"{line}\n{out.err}"
        if argv[0] == "run":
            versions.append(out.out.strip())
        outputs[argv[0]] = out.out
    assert json.loads((tmp_path / "rig.json").read_text())["version"] == versions[0]
    result = json.loads(outputs["compare"])
    assert result["kind"] == "rig" and result["flagged"] is False
    rows = outputs["history"].splitlines()[2:]                   # the header and its rule first
    assert [r.split()[2] for r in rows] == ["bar2-right", "bar2-right"]
