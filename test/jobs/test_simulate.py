"""robot_ct_ros.jobs.simulate: the phantoms robot-ct simulate offers."""

from __future__ import annotations

import numpy as np
import pytest

from robot_ct_ros.jobs.simulate import PHANTOMS, make_phantom


@pytest.mark.parametrize("name", PHANTOMS)
def test_each_offered_phantom_is_made_around_the_roi_it_centres_on(name):
    """Every phantom of PHANTOMS exists and holds the origin (the ROI's centre) inside its bounds; the seed
    draws its random details, the same seed the same phantom."""
    lo, hi = (np.asarray(b, float) for b in make_phantom(name, 0).bounds_mm())
    assert np.all(lo < 0.0) and np.all(hi > 0.0)
    np.testing.assert_array_equal(np.asarray(make_phantom(name, 1).bounds_mm()),
                                  np.asarray(make_phantom(name, 1).bounds_mm()))


def test_an_unknown_phantom_is_refused_with_the_choices():
    with pytest.raises(ValueError, match="unknown phantom 'leg'.*carotid"):
        make_phantom("leg")
