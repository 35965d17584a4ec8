"""The compiled fit of the path predictor equals its numpy reference (``Predictor._refit``), to rounding."""

from __future__ import annotations

import copy

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from server.select import kernels
from server.select.predict import Predictor


@settings(max_examples=80, deadline=None)
@given(seed=st.integers(0, 2**31), n=st.integers(1, 40), jitter=st.sampled_from([0.0, 0.01, 0.5]),
       outliers=st.booleans())
def test_the_compiled_fit_equals_the_reference(seed, n, jitter, outliers):
    rng = np.random.default_rng(seed)
    p = Predictor()
    t = np.sort(rng.uniform(0, 0.9, n))
    speed, turn = rng.normal(0, 5, 3), rng.normal(0, 0.5)
    for ti in t:
        eye = speed * ti + rng.normal(0, jitter, 3)
        if outliers and rng.random() < 0.1:
            eye = eye + 30.0
        a = turn * ti
        p.add(ti, eye, [np.cos(a), np.sin(a), rng.normal(0, jitter * 0.1)], [0.0, 0.0, 1.0])
    ref, got = copy.deepcopy(p), copy.deepcopy(p)
    kernels.use_kernels(False)
    try:
        ref._refit()
    finally:
        kernels.use_kernels(None)
    kernels.use_kernels(True)
    try:
        got._refit()
    finally:
        kernels.use_kernels(None)
    for x, y in ((ref._a, got._a), (ref._b, got._b)):
        assert np.allclose(x, y, rtol=1e-9, atol=1e-9 * max(1.0, np.abs(x).max()))
    assert np.isclose(ref._speed_seen, got._speed_seen, rtol=1e-9) and np.isclose(ref._turn_seen, got._turn_seen,
                                                                                   rtol=1e-9, atol=1e-12)
