"""One rig session's calibration as plain steps: prepare (validate, nothing written), solve, commit.

A rig session (CONTRACT section 3, "Rig sessions") that carries ``observations.csv`` is
calibrated by :func:`fieldcal.rig.adjust_rig`; its results are one calibration document per
head and the rig document (:mod:`fieldcal.rig.document`), committed to the lake as one version
of the rig by :meth:`fieldcal.lake.store.Lake.commit_rig`.

Fingerprints: the rig's is that of its inputs (session.json, targets.csv, observations.csv)
and settings; each head's is the rig's with the head's id, so that a head's version is
recognised as the same inputs and a rerun finds it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from fieldcal.errors import InputError
from fieldcal.pipeline import Settings
from fieldcal.rig.data import RigData
from fieldcal.rig.session import RigSession, load_rig_session, rig_data_from_observations
from fieldcal.session.fingerprint import fingerprint, sha256_bytes

__all__ = ["RigPrepared", "RigOutcome", "prepare_rig", "solve_rig", "run_rig"]


@dataclass
class RigPrepared:
    """A validated rig session, its data and its inputs' fingerprint."""

    session: RigSession
    settings: Settings
    data: RigData
    fingerprint: str


@dataclass
class RigOutcome:
    """What :func:`solve_rig` produced: per head what :meth:`Lake.commit_rig` takes, the rig
    document (its versions filled in at the commit) and a human summary."""

    heads: list
    rig_document: dict
    summary: list
    result: object = None


def prepare_rig(folder, settings: Settings | None = None) -> RigPrepared:
    """Validate a rig session and read its observations; nothing is written.

    Raises
    ------
    InputError
        One line naming the file and what is wrong (also: a rig session without
        ``observations.csv``, which this version of fieldcal cannot measure from images).
    """
    settings = settings or Settings()
    if settings.solver not in ("lmqn", "lm"):
        raise InputError(f"solver must be 'lmqn' or 'lm', got {settings.solver!r}", "settings")
    sess = load_rig_session(folder)
    if sess.observations_path is None:
        raise InputError("a rig session needs observations.csv (measuring a rig's images is not supported yet)",
                         str(sess.folder))
    data = rig_data_from_observations(sess)
    parts = {"session": sha256_bytes((sess.folder / "session.json").read_bytes()),
             "targets": sha256_bytes(sess.targets_path.read_bytes()),
             "observations": sha256_bytes(sess.observations_path.read_bytes()),
             "settings": settings.to_dict(), "kind": "rig"}
    return RigPrepared(sess, settings, data, fingerprint(parts))


def solve_rig(prepared: RigPrepared, *, progress: Callable[[str], None] | None = None) -> RigOutcome:
    """Adjust the rig and make its documents (module docstring)."""
    from fieldcal.rig.adjustment import RigOptions, adjust_rig
    from fieldcal.rig.document import head_arrays, head_document, head_residual_table, rig_document

    sess, st = prepared.session, prepared.settings
    options = RigOptions(targets_adjusted=st.targets_adjusted, estimate=sess.estimate, method=st.solver)
    res = adjust_rig(prepared.data, options, progress=progress)
    acquired = sess.acquired.strftime("%Y-%m-%dT%H:%M:%SZ")
    heads = []
    for h, hd in enumerate(prepared.data.heads):
        fp = fingerprint({"rig": prepared.fingerprint, "camera_id": hd.camera_id})
        arrays, attrs = head_arrays(res, h)
        heads.append({"document": head_document(res, h, session_id=sess.session_id, fingerprint=fp, acquired=acquired),
                      "arrays": arrays, "array_attrs": attrs, "residuals": head_residual_table(res, h)})
    rig = rig_document(res, session_id=sess.session_id, head_versions=[""] * len(heads),
                       fingerprint=prepared.fingerprint, acquired=acquired)
    return RigOutcome(heads, rig, _summary(prepared, res), res)


def _summary(prepared: RigPrepared, res) -> list[str]:
    st = res.stats()
    lines = [f"rig {prepared.data.rig_id} / {prepared.session.session_id}: {len(prepared.data.heads)} heads, "
             f"{st['n_exposures']} exposures, {st['n_images']} images, {st['n_observations']} points "
             f"({st['n_rejected']} rejected), sigma0 {st['sigma0']:.3f}"]
    for h, hd in enumerate(prepared.data.heads):
        hs = st["heads"][hd.camera_id]
        f, sf = res.state.params[h][0], res.sigma[h].get("f_mm")
        rot, t = res.sigma_rotation_arcsec[h], res.sigma_t_mm[h]
        rel = ("reference" if h == prepared.data.reference else
               f"sigma rotation {', '.join(f'{v:.2g}' for v in rot)} arcsec, "
               f"lever arm {', '.join(f'{v:.2g}' for v in t)} mm")
        lines.append(f"  {hd.camera_id}: f {f:.5f} ± {sf:.2g} mm, rmse {hs['rmse_px']:.3g} px; {rel}")
    return lines


def run_rig(folder, lake, *, settings: Settings | None = None, force: bool = False,
            progress: Callable[[str], None] | None = None, prepared: RigPrepared | None = None):
    """Prepare (unless ``prepared`` is given), solve and commit a rig session; returns ``(rig
    version, head versions, outcome)`` (``outcome`` None when the same inputs were committed
    already and nothing was solved)."""
    prepared = prepared if prepared is not None else prepare_rig(folder, settings)
    if not force:
        hit = lake.rig_catalog(fingerprint=prepared.fingerprint)
        if hit.num_rows:
            return hit["version"][-1].as_py(), hit["head_versions"][-1].as_py(), None
    outcome = solve_rig(prepared, progress=progress)
    version, heads = lake.commit_rig(outcome.heads, outcome.rig_document, force=force)
    return version, heads, outcome
