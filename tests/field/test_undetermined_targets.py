"""A target whose survey is rejected is determined only by rays from different places (issue 23:
two rolls from one station left the first adjustment of a rendered faceted session singular)."""

import numpy as np

from fieldcal.field.adjustment import _drop_undetermined_targets
from fieldcal.synthetic.field import wide_field


def _two_images_of(sf, t, same_station: bool):
    obs = sf.data.obs
    imgs = obs.image[obs.target == t]
    st = np.array([sf.data.images[i].station for i in imgs])
    if same_station:
        s = next(s for s in st if np.sum(st == s) >= 2)
        return imgs[st == s][:2]
    return np.array([imgs[0], imgs[np.flatnonzero(st != st[0])[0]]])


def test_two_rolls_from_one_station_do_not_determine_a_target_without_its_survey():
    sf = wide_field(seed=0)
    obs = sf.data.obs
    t = int(np.bincount(obs.target).argmax())
    survey = np.ones(len(sf.data.targets), bool)
    survey[t] = False
    for same, dropped in ((True, True), (False, False)):
        two = _two_images_of(sf, t, same)
        active = (obs.target != t) | np.isin(obs.image, two)
        reason = np.full(len(obs), "", object)
        n = _drop_undetermined_targets(sf.data, active, survey, reason, sf.targets_true.xyz_m, sf.center_m)
        assert n == (2 if dropped else 0)
        assert np.all(active[obs.target != t])
        mine = (obs.target == t) & np.isin(obs.image, two)
        assert np.all(active[mine] != dropped)
        assert set(reason[mine]) == {"target undetermined after its survey was rejected" if dropped else ""}
        # without the geometry two images suffice (the rule as it was)
        active = (obs.target != t) | np.isin(obs.image, two)
        assert _drop_undetermined_targets(sf.data, active, survey, reason) == 0
