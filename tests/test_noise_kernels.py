"""One-pass Monte Carlo kernels: numba == numpy reference, analytic cases."""

from __future__ import annotations

import numpy as np
import pytest

from xstack.noise import kernels as K


def _case(rng, nrow=300, nchan=7, npos=40, even=True):
    uvw = rng.normal(0, 3e3, (nrow, 3))
    freq = 1.4e9 + np.arange(nchan) * 20e6
    if not even:
        freq = freq + rng.uniform(0, 5e6, nchan)
    vw = rng.normal(size=(nrow, nchan)) + 1j * rng.normal(size=(nrow, nchan))
    ws = rng.uniform(0.5, 2, (nrow, nchan))
    ws[::17] = 0.0  # flagged rows are skipped
    vw[::17] = 0.0
    l = rng.normal(0, 5e-3, npos)
    m = rng.normal(0, 5e-3, npos)
    n1 = -(l * l + m * m) / (1 + np.sqrt(1 - l * l - m * m))
    a = rng.uniform(0.2, 1, (nchan, npos))
    b = rng.uniform(0, 1, (nchan, npos))
    return uvw, freq, vw, ws, l, m, n1, a, b


@pytest.mark.parametrize("even", [True, False])
def test_group_sums_match_numpy(rng, even):
    uvw, freq, vw, ws, l, m, n1, a, b = _case(rng, even=even)
    starts = np.array([0, 5, 5, 23, 40])  # includes an empty group
    bins = rng.integers(-1, 6, vw.shape)
    got = K.group_sums(uvw, freq, vw, ws, l, m, n1, a, b, starts, bins=bins, nbins=6, reseed=3)
    ref = K.group_sums_numpy(uvw, freq, vw, ws, l, m, n1, a, b, starts, bins=bins, nbins=6)
    for x, y in zip(got, ref):
        np.testing.assert_allclose(x, y, rtol=1e-10, atol=1e-10 * np.abs(y).max())
    d, mdl, _, _ = K.group_sums(uvw, freq, vw, ws, l, m, n1, a, None, starts)
    np.testing.assert_allclose(d, ref[0], rtol=1e-10, atol=1e-10 * np.abs(ref[0]).max())
    assert np.all(mdl == 0)
    X = K.position_sums(uvw, freq, vw, ws, l, m, n1, a)
    np.testing.assert_allclose(X, K.position_sums_numpy(uvw, freq, vw, ws, l, m, n1, a),
                               rtol=1e-10, atol=1e-10 * np.abs(X).max())
    # the data term of a group is the sum of its positions' terms (linearity)
    np.testing.assert_allclose([X[s:e].sum() for s, e in zip(starts[:-1], starts[1:])], d,
                               rtol=1e-9, atol=1e-9 * np.abs(d).max())


def test_point_source_recovered_exactly(rng):
    """A source of flux S at position k (eq. 1) stacks to S * sum(W) at k, analytically."""
    uvw, freq, _, ws, l, m, n1, _, _ = _case(rng, npos=3)
    S = 2.5
    d = uvw[:, 0:1] * l[1] + uvw[:, 1:2] * m[1] + uvw[:, 2:3] * n1[1]
    vis = S * np.exp(2j * np.pi * d * freq[None] / 299792458.0)
    vw = ws * vis
    X = K.position_sums(uvw, freq, vw, ws, l, m, n1, np.ones((freq.size, 3)))
    assert X[1] == pytest.approx(S * ws.sum(), rel=1e-12)
    # and the injected model alone (no data) gives the same, through the model term
    data, model, _, _ = K.group_sums(uvw, freq, np.zeros_like(vw), ws, l[1:2], m[1:2], n1[1:2],
                                     np.ones((freq.size, 1)), np.full((freq.size, 1), S),
                                     np.array([0, 1]))
    assert data[0] == 0 and model[0] == pytest.approx(S * ws.sum(), rel=1e-12)


def test_long_recurrence_stays_accurate(rng):
    """200 evenly spaced channels, long baselines: recurrence with re-seeding vs np.exp."""
    uvw, _, _, _, l, m, n1, _, _ = _case(rng, nrow=50, npos=8)
    uvw *= 30.0
    freq = 1.0e9 + np.arange(200) * 1e6
    vw = rng.normal(size=(50, 200)) + 1j * rng.normal(size=(50, 200))
    ws = np.ones((50, 200))
    a = np.ones((200, 8))
    X = K.position_sums(uvw, freq, vw, ws, l, m, n1, a)
    ref = K.position_sums_numpy(uvw, freq, vw, ws, l, m, n1, a)
    np.testing.assert_allclose(X, ref, rtol=0, atol=1e-9 * np.abs(vw).sum() / 8)
    assert K.channels_evenly_spaced(freq) and not K.channels_evenly_spaced(freq**1.01)


# ------------------------------------------------------------------ antenna factorisation

def _antenna_case(rng, *, nant=7, ntime=9, nchan=7, npos=40, even=True):
    """Rows (time, baseline) whose UVW are differences of per-antenna UVW (w-term large)."""
    from xstack.schema import baseline_pairs

    a1, a2 = baseline_pairs(nant)
    ant = rng.normal(0, 3e3, (ntime, nant, 3))
    uvw = (ant[:, a1] - ant[:, a2]).reshape(-1, 3)
    _, freq, vw, ws, l, m, n1, a, b = _case(rng, nrow=uvw.shape[0], nchan=nchan, npos=npos,
                                            even=even)
    # far positions (a few degrees): the w-term phase is many turns
    l, m = l * 10, m * 10
    n1 = -(l * l + m * m) / (1 + np.sqrt(1 - l * l - m * m))
    return uvw, a1, a2, freq, vw, ws, l, m, n1, a, b


def _assert_sums_equal(got, ref, rtol=1e-9):
    for x, y in zip(got, ref):
        scale = np.abs(y).max() if y.size else 0.0
        np.testing.assert_allclose(x, y, rtol=rtol, atol=rtol * scale)


@pytest.mark.parametrize("even", [True, False])
def test_antenna_path_matches_numpy(rng, even):
    uvw, a1, a2, freq, vw, ws, l, m, n1, a, b = _antenna_case(rng, even=even)
    nbl = a1.size
    # a fully flagged time, an antenna missing at one time, zero-weight rows with NaN or
    # inconsistent UVW (they must neither count nor spoil the antenna solution)
    ws[2 * nbl:3 * nbl] = 0.0
    t4 = slice(4 * nbl, 5 * nbl)
    ws[t4][(a1 == 3) | (a2 == 3)] = 0.0
    uvw[5 * nbl + 2] = np.nan
    ws[5 * nbl + 2] = 0.0
    uvw[6 * nbl + 4] += 1.0
    ws[6 * nbl + 4] = 0.0
    vw[ws == 0] = 0.0
    starts = np.array([0, 5, 5, 23, 40])  # includes an empty group
    bins = rng.integers(-1, 6, vw.shape)
    layout = K.antenna_layout(uvw, a1, a2, row_ok=np.any(ws > 0, axis=1))
    assert not layout.used[4, 3] and layout.used[4, 2] and not layout.used[2].any()
    assert layout.phase_error(l, m, n1, freq) < 1e-10
    assert layout.rows_per_antenna > 2
    got = K.group_sums_antenna(layout, freq, vw, ws, l, m, n1, a, b, starts, bins=bins,
                               nbins=6, reseed=3)
    clean = np.nan_to_num(uvw)
    ref = K.group_sums_numpy(clean, freq, vw, ws, l, m, n1, a, b, starts, bins=bins, nbins=6)
    _assert_sums_equal(got, ref)
    # and the per-row kernel agrees with both
    _assert_sums_equal(K.group_sums(clean, freq, vw, ws, l, m, n1, a, b, starts, bins=bins,
                                    nbins=6, reseed=3), ref)
    d, mdl, _, _ = K.group_sums_antenna(layout, freq, vw, ws, l, m, n1, a, None, starts)
    np.testing.assert_allclose(d, ref[0], rtol=1e-9, atol=1e-9 * np.abs(ref[0]).max())
    assert np.all(mdl == 0)


def test_antenna_path_arbitrary_antenna_ids_and_long_recurrence(rng):
    """Antenna ids with gaps, baselines in any order, 64 even channels (re-seeding)."""
    uvw, a1, a2, _, _, _, l, m, n1, _, b = _antenna_case(rng, nant=6, ntime=4, npos=12)
    perm = rng.permutation(a1.size)
    ids = np.array([3, 8, 9, 20, 21, 40])
    a1, a2 = ids[a1[perm]], ids[a2[perm]]
    uvw = uvw.reshape(4, -1, 3)[:, perm].reshape(-1, 3)
    freq = 1.0e9 + np.arange(64) * 2e6
    nrow = uvw.shape[0]
    vw = rng.normal(size=(nrow, 64)) + 1j * rng.normal(size=(nrow, 64))
    ws = rng.uniform(0.5, 2, (nrow, 64))
    a = rng.uniform(0.2, 1, (64, 12))
    b = rng.uniform(0, 1, (64, 12))
    starts = np.array([0, 7, 12])
    layout = K.antenna_layout(uvw, a1, a2)
    got = K.group_sums_antenna(layout, freq, vw, ws, l, m, n1, a, b, starts)
    _assert_sums_equal(got, K.group_sums_numpy(uvw, freq, vw, ws, l, m, n1, a, b, starts))


def test_antenna_path_refuses_inconsistent_uvw(rng):
    uvw, a1, a2, freq, vw, ws, l, m, n1, a, b = _antenna_case(rng, ntime=3, npos=6)
    starts = np.array([0, 6])
    bad = uvw.copy()
    bad[a1.size + 5] += [1e-3, 0.0, 0.0]  # 1 mm on one used row
    layout = K.antenna_layout(bad, a1, a2)
    assert layout.phase_error(l, m, n1, freq) > 1e-6
    with pytest.raises(K.FactorisationError, match="phase error"):
        K.group_sums_antenna(layout, freq, vw, ws, l, m, n1, a, b, starts)
    # rows with weight that the solution was not fitted to
    layout = K.antenna_layout(uvw, a1, a2, row_ok=np.arange(uvw.shape[0]) % 2 == 0)
    with pytest.raises(K.FactorisationError, match="not part"):
        K.group_sums_antenna(layout, freq, vw, ws, l, m, n1, a, b, starts)
    # rows that are not whole times of the baselines
    with pytest.raises(K.FactorisationError, match="whole times"):
        K.antenna_layout(uvw[:-1], a1, a2)
