"""Bad scans: NaN rows and single points get an InputError naming the argument (issue 38)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gatv import register, register_scans
from gatv.errors import InputError


def _scan(n=200, seed=0):
    """A small patch of a curved surface (what the scans pipeline takes)."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform(-1.0, 1.0, (n, 2))
    return np.column_stack([uv, 0.3 * uv[:, 0] ** 2 - 0.2 * uv[:, 1] ** 2])


@settings(max_examples=20, deadline=None)
@given(which=st.sampled_from(["source", "target"]), rows=st.sets(st.integers(0, 199), min_size=1, max_size=5),
       value=st.sampled_from([np.nan, np.inf, -np.inf]), column=st.integers(0, 2),
       call=st.sampled_from(["register", "register_scans"]))
def test_a_scan_with_nan_rows_is_named(which, rows, value, column, call):
    good = _scan()
    bad = good.copy()
    bad[sorted(rows), column] = value
    source, target = (bad, good) if which == "source" else (good, bad)
    with pytest.raises(InputError, match=f"`{which}`") as caught:
        if call == "register":
            register(source, target, pipeline="scans")
        else:
            register_scans(source, target)
    # The message says what to do about it, and does not blame the other scan.
    assert "remove or replace" in str(caught.value)
    other = "target" if which == "source" else "source"
    assert f"`{other}`" not in str(caught.value)


@pytest.mark.parametrize("which", ["source", "target"])
@pytest.mark.parametrize("pipeline", ["scans", None])
def test_a_single_point_scan_is_named(which, pipeline):
    good = _scan()
    one = good[:1]
    source, target = (one, good) if which == "source" else (good, one)
    with pytest.raises(InputError, match=f"`{which}`.*at least 3 points, got 1"):
        register(source, target, **({"pipeline": pipeline} if pipeline else {}))


@pytest.mark.parametrize("which", ["source", "target"])
def test_an_empty_scan_is_named(which):
    good = _scan()
    empty = np.empty((0, 3))
    source, target = (empty, good) if which == "source" else (good, empty)
    with pytest.raises(InputError, match=f"`{which}`"):
        register_scans(source, target)


@pytest.mark.parametrize("name", ["tol", "stall"])
@pytest.mark.parametrize("bad", [-1e-9, np.nan, np.inf, "1e-9", None])
def test_a_bad_point_to_plane_tolerance_is_named(bad, name):
    from gatv.scans import refine_point_to_plane

    target = _scan()
    normals = np.tile([0.0, 0.0, 1.0], (target.shape[0], 1))
    with pytest.raises(InputError, match=f"`{name}` to be a finite number >= 0"):
        refine_point_to_plane(target, target, normals, np.eye(3), np.zeros(3), 0.1, **{name: bad})


@pytest.mark.parametrize("bad", ["yes", 1, None, 0.0])
def test_a_bad_coarse_first_is_named(bad):
    good = _scan()
    with pytest.raises(InputError, match="`coarse_first` True or False"):
        register_scans(good, good, coarse_first=bad)
