"""uv-stack error bars that do not trust WEIGHT: the noise measured from the visibilities.

Truths from outside the code under test: a plain-numpy twin of the pair-difference
estimator, the known sigma of simulated noise, the brute-force scatter of the stacked flux
over independent noise realisations (plain-numpy stack with an independent eq.-4 phasor),
and python-casacore reads of the real EVLA MS shipped in the pyuvdata wheel.
"""

from __future__ import annotations

import inspect
import json
import warnings

import dask
import numpy as np
import pytest
import xarray as xr
from _uvstack_helpers import VLA_CENTER, direct_eq4, make_stack_partition
from astropy.table import Table

from xstack import _scatter
from xstack.cli import main
from xstack.coords import lm_to_radec, radec_to_lmn
from xstack.schema import write_store
from xstack.uvstack import kernels as K
from xstack.uvstack.stack import stack_uv

MISSCALED = "differ by"


# --- the estimator against a plain-numpy twin and the known sigma --------------------------

def _disjoint_differences(v, g, w=None):
    """Differences of disjoint neighbour pairs along the last axis, runs of good cells;
    with weights ``w`` each divided by sqrt(1/w1 + 1/w2)."""
    out = []
    w = np.full(v.shape, 2.0) if w is None else np.asarray(w, dtype=np.float64)  # 2: no scaling
    for row, ok, wr in zip(v, g, w):
        c = 0
        while c + 1 < row.size:
            if ok[c] and ok[c + 1]:
                out.append((row[c + 1] - row[c]) / np.sqrt(1 / wr[c] + 1 / wr[c + 1]))
                c += 2
            else:
                c += 1
    return np.array(out, dtype=np.complex128)


def _mad_var(d):
    dev = np.concatenate([np.abs(d.real - np.median(d.real)), np.abs(d.imag - np.median(d.imag))])
    return (1.482602218505602 * np.median(dev)) ** 2 * dev.size / (dev.size - 2.6)


def _numpy_pair_variance(vis, weight, flag, min_pairs, max_pairs=10**9):
    """Plain numpy: per (baseline, pol) MAD of differences of disjoint neighbouring cells."""
    nt, nb, nc, npol = vis.shape
    good = ~flag & (weight > 0) & np.isfinite(vis.real) & np.isfinite(vis.imag)
    out = np.full((nb, npol), np.nan)
    for b in range(nb):
        for p in range(npol):
            v, g = vis[:, b, :, p], good[:, b, :, p]
            d = _disjoint_differences(v, g) if nc > 1 else _disjoint_differences(v.T, g.T)
            if d.size < max(min_pairs, 1):
                continue
            out[b, p] = 0.5 * _mad_var(d[::-(-d.size // max_pairs)])
    return out


def _random_block(rng, nt, nb, nc, npol, sigma):
    shape = (nt, nb, nc, npol)
    s = np.asarray(sigma)[None, :, None, None]
    vis = s * (rng.normal(size=shape) + 1j * rng.normal(size=shape))
    weight = rng.uniform(0.5, 2.0, size=shape)  # unrelated to sigma on purpose
    flag = rng.uniform(size=shape) < 0.1
    vis[rng.uniform(size=shape) < 0.02] = np.nan  # NaN data (some flagged, some not)
    weight[rng.uniform(size=shape) < 0.05] = 0.0
    return vis.astype(np.complex64), weight.astype(np.float32), flag


@pytest.mark.parametrize("nc", [16, 1])
def test_pair_variance_matches_numpy_and_known_sigma(nc):
    rng = np.random.default_rng(3)
    nt = 40 if nc > 1 else 400
    sigma = rng.uniform(0.5, 3.0, size=6)
    vis, weight, flag = _random_block(rng, nt, 6, nc, 2, sigma)
    var, npairs, invw = _scatter.pair_variance(vis, weight, flag)
    want = _numpy_pair_variance(vis.astype(np.complex128), weight, flag, _scatter.MIN_PAIRS)
    np.testing.assert_allclose(var, want, rtol=1e-12)
    # thinned to every k-th pair
    thin, _, _ = _scatter.pair_variance(vis, weight, flag, max_pairs=37)
    np.testing.assert_allclose(thin, _numpy_pair_variance(vis.astype(np.complex128), weight, flag,
                                                          _scatter.MIN_PAIRS, 37), rtol=1e-12)
    assert not np.allclose(thin, var)
    good = ~flag & (weight > 0) & np.isfinite(vis)
    np.testing.assert_allclose(invw[:, 0], [np.mean(1 / weight[:, b, :, 0][good[:, b, :, 0]])
                                            for b in range(6)], rtol=1e-6)
    assert np.all(npairs > 120)
    # the truth: sigma^2 of the simulated noise, to the MAD's sampling error (~ 2.4/sqrt(2n))
    rel = var / sigma[:, None] ** 2 - 1
    assert np.all(np.abs(rel) < 4 * 1.7 / np.sqrt(2 * npairs)), rel
    # per cell: the estimate on data cells, NaN elsewhere
    cell = _scatter.empirical_variance(vis, weight, flag)
    assert cell.shape == vis.shape
    assert np.array_equal(np.isfinite(cell), good)
    np.testing.assert_allclose(cell[good], np.broadcast_to(var[None, :, None, :], vis.shape)[good])


def test_pair_variance_unbiased_over_many_small_samples():
    # 20 pairs per (baseline, pol): the small-sample correction keeps the mean unbiased
    rng = np.random.default_rng(5)
    vis = 2.0 * (rng.normal(size=(5, 4000, 9, 1)) + 1j * rng.normal(size=(5, 4000, 9, 1)))
    var, n, _ = _scatter.pair_variance(vis, np.ones(vis.shape), np.zeros(vis.shape, bool))
    assert np.all(n == 20)
    assert np.mean(var) == pytest.approx(4.0, rel=0.015)


def test_too_few_pairs_pool_then_weights():
    rng = np.random.default_rng(8)
    vis, weight, flag = _random_block(rng, 10, 4, 8, 2, np.ones(4))
    flag[:, 1] = True
    flag[:, 1, 0, :] = False  # one channel per time: no channel pair on baseline 1
    var, npairs, _ = _scatter.pair_variance(vis, weight, flag, pol_mask=[True, False])
    assert np.all(np.isnan(var[:, 1]))  # correlation not asked for
    assert npairs[1, 0] == 0 and np.isnan(var[1, 0])
    assert np.all(np.isfinite(var[[0, 2, 3], 0]))
    model = _scatter.noise_model(vis, weight, flag)
    assert np.all(model[1, :, 2] == _scatter.POOLED) and np.all(model[[0, 2, 3], :, 2] == _scatter.OWN)
    # pooled: the weights rescaled by the MAD scale of all the block's weight-normalised pairs
    good = ~flag & (weight > 0) & np.isfinite(vis)
    v = vis.astype(np.complex128)
    z = np.concatenate([_disjoint_differences(v[:, b, :, p], good[:, b, :, p], weight[:, b, :, p])
                        for b in range(4) for p in range(2)])
    scale = _mad_var(z)
    assert scale == pytest.approx(1.0, rel=0.3)  # unit noise, weights uniform(0.5, 2): ~1.3 avg
    assert np.all(model[1, :, 1] == pytest.approx(scale, rel=1e-12))
    assert _scatter.pooled_weight_scale(vis, weight, flag)[0] == pytest.approx(scale, rel=1e-12)
    full, _, _ = _scatter.pair_variance(vis, weight, flag)
    assert np.all(model[1, :, 0] == 0) and np.all(model[0, :, 1] == 0)
    np.testing.assert_allclose(model[[0, 2, 3], :, 0], full[[0, 2, 3]])
    # nothing estimable in the block (one integration, one channel): the weights as they are
    one = _scatter.noise_model(vis[:1, :, :1], weight[:1, :, :1], flag[:1, :, :1])
    assert np.all(one[..., 2] == _scatter.WEIGHTS) and np.all(one[..., 1] == 1.0)


def test_stack_sums_with_noise_match_numpy():
    rng = np.random.default_rng(9)
    vis, weight, flag = _random_block(rng, 7, 5, 6, 2, np.arange(1, 6))
    flag[:, 3] = True
    flag[:, 3, 0] = False  # baseline 3 pools
    model = _scatter.noise_model(vis, weight, flag)
    n = 7 * 5
    ph = np.exp(1j * rng.uniform(0, 6.3, size=(n, 6))) * rng.uniform(0.2, 1, size=(n, 6))
    args = (vis.reshape(n, 6, 2), weight.reshape(n, 6, 2), flag.reshape(n, 6, 2), ph)
    got = K.stack_sums(*args, noise=model)
    want = K.stack_sums_numpy(*args, noise=model)
    np.testing.assert_allclose(got, want, rtol=1e-10)
    assert got.size == K.NSUMS and got[6] > 0 and got[7] == 0
    # plain check of the measured-variance sum: sum w^2 sigma_e^2 |P|^2 over the data cells
    good = ~flag & (weight > 0) & np.isfinite(vis)
    w = np.where(good, weight, 0).astype(np.float64)
    sig2 = model[None, :, None, :, 0] + model[None, :, None, :, 1] / np.where(w > 0, w, 1)
    p2 = np.abs(ph.reshape(7, 5, 6, 1)) ** 2
    assert got[5] == pytest.approx(np.sum(w**2 * sig2 * p2), rel=1e-10)
    # without a model the measured sum is the weights' sum
    plain = K.stack_sums(*args)
    assert plain[5] == pytest.approx(plain[2]) and plain[7] == plain[4]


# --- the stacked flux error against brute force over noise realisations --------------------

def _case(kind):
    """A noise template (sigma per baseline), the WEIGHT it carries, and a catalog."""
    rng = np.random.default_rng(11)
    ds = make_stack_partition(n_time=8, n_ant=6, n_chan=8, sigma=1.0, seed=1)
    nb = ds.sizes["baseline_id"]
    if kind == "x100":  # WEIGHT 100x too large: errors 10x too small
        sigma_b = np.ones(nb)
        factor = np.full(nb, 100.0)
    elif kind == "per-baseline":  # noise and the weights' error both differ per baseline
        sigma_b = rng.uniform(0.5, 2.0, nb)
        factor = 10 ** rng.uniform(-1.5, 1.5, nb)
    else:  # honest weights, noise differs per baseline
        sigma_b = rng.uniform(0.5, 2.0, nb)
        factor = np.ones(nb)
    wt = np.broadcast_to((factor / sigma_b**2)[None, :, None, None], ds["WEIGHT"].shape)
    ds["WEIGHT"] = (ds["WEIGHT"].dims, wt.astype(np.float32))
    l = rng.uniform(-0.004, 0.006, 12)
    m = rng.uniform(-0.004, 0.006, 12)
    ra, dec = lm_to_radec(l, m, *VLA_CENTER)
    return ds, sigma_b, Table({"ra": np.degrees(ra), "dec": np.degrees(dec)})


def _noise(rng, shape, sigma_b):
    s = sigma_b[None, :, None, None]
    return s * (rng.normal(size=shape) + 1j * rng.normal(size=shape))


def _brute_force_std(ds, sigma_b, cat, n_real):
    """Plain numpy: the stacked flux (weights none, no beam) over n_real noise realisations."""
    uvw = np.asarray(ds["UVW"].values)
    freq = np.asarray(ds["frequency"].values)
    l, m, n, _ = radec_to_lmn(np.radians(cat["ra"]), np.radians(cat["dec"]), *VLA_CENTER)
    k = len(cat)
    ph = direct_eq4(uvw.reshape(-1, 3), freq, l, m, n, np.ones(k), np.ones((k, freq.size)))
    ph = ph.reshape(uvw.shape[:2] + (freq.size, 1))
    w = np.asarray(ds["WEIGHT"].values, dtype=np.float64)
    rng = np.random.default_rng(2024)
    flux = [np.sum(w * (_noise(rng, w.shape, sigma_b) * ph).real) / np.sum(w)
            for _ in range(n_real)]
    return float(np.std(flux, ddof=1)), ph


#: plain eq. 4 (the brute force has no smearing correction)
PLAIN = {"smearing": "none"} if "smearing" in inspect.signature(stack_uv).parameters else {}


CLI_PLAIN = ["--smearing", "none"] if PLAIN else []


def _stack(ds, cat, vis):
    d = ds.copy()
    d["VISIBILITY"] = (ds["VISIBILITY"].dims, vis)
    return stack_uv(xr.DataTree.from_dict({"spw0_field0": d}), cat, weighting="none",
                   primary_beam="none", **PLAIN)


@pytest.mark.parametrize("kind", ["x100", "per-baseline", "honest"])
def test_empirical_error_matches_brute_force(kind):
    ds, sigma_b, cat = _case(kind)
    n_real = 400  # std of the brute-force std: 1/sqrt(2 * 399) = 3.5 %
    truth, ph = _brute_force_std(ds, sigma_b, cat, n_real)
    rng = np.random.default_rng(77)
    emp, wts, msgs = [], [], []
    w = np.asarray(ds["WEIGHT"].values, dtype=np.float64)
    with dask.config.set(scheduler="synchronous"):
        for _ in range(6):
            vis = _noise(rng, ds["VISIBILITY"].shape, sigma_b)
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                res = _stack(ds, cat, vis)
            msgs.append([str(c.message) for c in caught if MISSCALED in str(c.message)])
            # the same flux as the plain-numpy stack of this realisation
            assert res.flux_jy == pytest.approx(np.sum(w * (vis * ph).real) / np.sum(w), abs=1e-12)
            emp.append(res.flux_err_empirical_jy)
            wts.append(res.flux_err_jy)
            assert res.noise_estimate == {"pairs": "channels", "own": res.n_visibilities,
                                          "pooled": 0, "weights": 0}
    emp_mean = np.mean(emp)
    # 3.5 % (brute force) and ~4 % per realisation / sqrt(6) (estimate): 15 % is > 3 sigma
    assert emp_mean / truth == pytest.approx(1.0, abs=0.15), (emp_mean, truth)
    if kind == "honest":
        assert np.mean(wts) / truth == pytest.approx(1.0, abs=0.1)
        assert all(not m for m in msgs)  # both errors agree: no warning
        assert all(abs(e / w - 1) < 0.2 for e, w in zip(emp, wts))
    else:
        # the weight-based error is wrong (10x for x100) and every run warns, naming errors
        assert abs(np.mean(wts) / truth - 1) > 0.5
        assert all(len(m) == 1 and "errors='empirical'" in m[0] for m in msgs)
        if kind == "x100":
            assert np.mean(wts) / truth == pytest.approx(0.1, rel=0.1)
            assert res.weight_scale == pytest.approx(100, rel=0.25)


def test_two_datasets_and_written_store(tmp_path):
    """Two datasets (each its own pointing, noise and weight error) against brute force; the
    shared-phasor path (out=) and time-chunked blocks give the same measured error."""
    ds_a, sig_a, cat = _case("x100")
    ds_b = make_stack_partition(n_time=8, n_ant=6, n_chan=8, sigma=1.0, seed=9)
    sig_b = np.full(ds_b.sizes["baseline_id"], 2.5)
    ds_b["WEIGHT"] = ds_b["WEIGHT"] * 0.5  # honest would be 1/2.5^2 = 0.16; claims 0.5
    # brute force: both pointings at the same center, every position in both (no beam), so
    # the partition factors s_p (= number of positions) cancel: one weighted mean
    truth_parts = []
    rng = np.random.default_rng(31)
    phs, ws = [], []
    for ds in (ds_a, ds_b):
        uvw = np.asarray(ds["UVW"].values)
        freq = np.asarray(ds["frequency"].values)
        l, m, n, _ = radec_to_lmn(np.radians(cat["ra"]), np.radians(cat["dec"]), *VLA_CENTER)
        k = len(cat)
        ph = direct_eq4(uvw.reshape(-1, 3), freq, l, m, n, np.ones(k), np.ones((k, freq.size)))
        phs.append(ph.reshape(uvw.shape[:2] + (freq.size, 1)))
        ws.append(np.asarray(ds["WEIGHT"].values, dtype=np.float64))
    den = sum(np.sum(w) for w in ws)
    for _ in range(400):
        truth_parts.append(sum(np.sum(w * (_noise(rng, w.shape, sg) * ph).real)
                               for w, ph, sg in zip(ws, phs, (sig_a, sig_b))) / den)
    truth = np.std(truth_parts, ddof=1)
    emp = []
    for i in range(6):
        trees = []
        for ds, sg in ((ds_a, sig_a), (ds_b, sig_b)):
            d = ds.copy()
            d["VISIBILITY"] = (ds["VISIBILITY"].dims, _noise(rng, ds["VISIBILITY"].shape, sg))
            trees.append(xr.DataTree.from_dict({"spw0_field0": d}))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = stack_uv(trees, cat, weighting="none", primary_beam="none", **PLAIN)
            emp.append(res.flux_err_empirical_jy)
            if i == 0:
                # written store (shared phasor) and blocks of 4 integrations: same error
                out = stack_uv(trees, cat, weighting="none", primary_beam="none", **PLAIN,
                              out=tmp_path / "s.zarr")
                chunked = [t.chunk({"time": 4}) for t in trees]
                blocks = stack_uv(chunked, cat, weighting="none", primary_beam="none", **PLAIN)
        assert len(res.partition_sums) == 2
    assert out.flux_err_empirical_jy == pytest.approx(emp[0], rel=1e-12)
    from xstack.schema import open_store

    attrs = open_store(tmp_path / "s.zarr").attrs["uvstack"]
    assert attrs["flux_err_empirical_jy"] == pytest.approx(emp[0], rel=1e-12)
    # 4 integrations x 4 pairs = 16 pairs per block: noisier per block, the same on average
    assert blocks.flux_err_empirical_jy == pytest.approx(emp[0], rel=0.15)
    assert blocks.noise_estimate["own"] + blocks.noise_estimate["pooled"] == blocks.n_visibilities
    assert np.mean(emp) / truth == pytest.approx(1.0, abs=0.15), (np.mean(emp), truth)
    assert res.flux_err_jy / truth < 0.6  # the weights' error is far off


def test_single_channel_uses_integrations_else_the_weights():
    _, _, cat = _case("x100")
    rng = np.random.default_rng(4)
    # 40 integrations of one channel: 20 disjoint time pairs per baseline and correlation
    ds = make_stack_partition(n_time=40, n_ant=6, n_chan=1, sigma=1.0, seed=1)
    ds["WEIGHT"] = ds["WEIGHT"] * 100
    ones = np.ones(ds.sizes["baseline_id"])
    with pytest.warns(UserWarning, match="errors='empirical'"):
        res = _stack(ds, cat, _noise(rng, ds["VISIBILITY"].shape, ones))
    assert res.noise_estimate == {"pairs": "integrations", "own": res.n_visibilities,
                                  "pooled": 0, "weights": 0}
    assert res.flux_err_empirical_jy / res.flux_err_jy == pytest.approx(10, rel=0.15)
    # 8 integrations: 4 pairs per baseline and correlation, fewer than MIN_PAIRS: pooled
    # over the block (15 baselines x 2 correlations x 4 pairs), still ~10x the weights
    ds8 = ds.isel(time=slice(0, 8))
    with pytest.warns(UserWarning, match="errors='empirical'"):
        res8 = _stack(ds8, cat, _noise(rng, ds8["VISIBILITY"].shape, ones))
    assert res8.noise_estimate["pooled"] == res8.n_visibilities
    assert res8.flux_err_empirical_jy / res8.flux_err_jy == pytest.approx(10, rel=0.3)
    # 3 antennas, 2 integrations: 6 pairs in the whole block, too few even to pool: the
    # weights as they are, said so in the result, and no warning (the errors agree)
    tiny = make_stack_partition(n_time=2, n_ant=3, n_chan=1, sigma=1.0, seed=2)
    tiny["WEIGHT"] = tiny["WEIGHT"] * 100
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res2 = _stack(tiny, cat, _noise(rng, tiny["VISIBILITY"].shape, np.ones(3)))
    assert res2.noise_estimate["weights"] == res2.n_visibilities
    assert res2.flux_err_empirical_jy == pytest.approx(res2.flux_err_jy, rel=1e-12)


def _cli_warns(capsys, argv, stream="out"):
    """Run the CLI; the mis-scaled-weights warning must come out (as a ``warning:`` line on
    stderr, or as a Python warning where the CLI leaves them to the caller)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rc = main(argv)
    cap = capsys.readouterr()
    lines = [str(c.message) for c in caught] + [x for x in cap.err.splitlines()
                                                if x.startswith("warning:")]
    assert sum("--errors" in x and MISSCALED in x for x in lines) == 1, lines
    return rc, cap.out if stream == "out" else cap.err


def test_cli_errors_choice_and_json(tmp_path, capsys):
    ds, sigma_b, cat = _case("x100")
    d = ds.copy()
    d["VISIBILITY"] = (ds["VISIBILITY"].dims,
                       _noise(np.random.default_rng(1), ds["VISIBILITY"].shape, sigma_b))
    data = tmp_path / "d.zarr"
    write_store({"spw0_field0": d}, data)
    catf = tmp_path / "cat.csv"
    cat.write(catf, format="ascii.csv")
    docs = {}
    for choice in ("weights", "empirical", None):
        extra = [] if choice is None else ["--errors", choice]
        out = tmp_path / f"o_{choice}.zarr"
        rc, out_text = _cli_warns(capsys, ["uvstack", str(data), str(catf), str(out),
                                           "--primary-beam", "none", "--weighting", "none",
                                           "--no-progress", "--json", *extra, *CLI_PLAIN])
        assert rc == 0
        docs[choice] = json.loads(out_text)
    doc = docs["weights"]
    assert doc["errors_first"] == "weights" and docs["empirical"]["errors_first"] == "empirical"
    # default auto: the weights are 100x off, so the measured error leads
    assert docs[None]["errors"] == "auto" and docs[None]["errors_first"] == "empirical"
    assert doc["flux_err_empirical_jy"] == pytest.approx(10 * doc["flux_err_jy"], rel=0.2)
    assert doc["weight_scale"] == pytest.approx(100, rel=0.4)
    # human output (the result, on stdout) leads with the chosen error
    rc, text = _cli_warns(capsys, ["uvstack", str(data), str(catf), str(tmp_path / "h.zarr"),
                                   "--primary-beam", "none", "--weighting", "none",
                                   "--no-progress", "--errors", "empirical", *CLI_PLAIN], "out")
    assert rc == 0
    line = next(x for x in text.splitlines() if x.startswith("stacked flux"))
    from xstack.cli._output import figure

    line_values = (doc["flux_jy"], doc["flux_err_jy"], doc["flux_err_empirical_jy"])
    lead = figure(doc["flux_jy"], doc["flux_err_empirical_jy"], "Jy", like=line_values)
    assert f"{lead} (from the visibility scatter" in line


# --- the real EVLA MS -----------------------------------------------------------------------

@pytest.fixture(scope="module")
def evla(tmp_path_factory):
    testing = pytest.importorskip("xstack.testing")
    convert = pytest.importorskip("xstack.io.convert")
    d = tmp_path_factory.mktemp("evla")
    ms = testing.require_real_ms("evla", d)
    return ms, convert.convert_ms(ms, d / "data.zarr")


def _casacore_sigma(ms):
    """Independent: per baseline and parallel hand, the 3-sigma clipped rms of channel
    differences / sqrt(2), from python-casacore reads of DATA, FLAG, WEIGHT_SPECTRUM."""
    ct = pytest.importorskip("casacore.tables")
    with ct.table(str(ms), ack=False) as t:
        data = t.getcol("DATA")
        flag = t.getcol("FLAG") | t.getcol("FLAG_ROW")[:, None, None]
        wsp = t.getcol("WEIGHT_SPECTRUM")
        a1, a2 = t.getcol("ANTENNA1"), t.getcol("ANTENNA2")
    sig, wts = {}, {}
    for key in sorted(set(zip(a1, a2))):
        rows = (a1 == key[0]) & (a2 == key[1])
        for p in (0, 3):  # RR, LL
            v, f = data[rows, :, p], flag[rows, :, p] | ~(wsp[rows, :, p] > 0)
            ok = ~f[:, 1:] & ~f[:, :-1]
            d = (v[:, 1:] - v[:, :-1])[ok]
            x = np.concatenate([d.real, d.imag])
            keep = np.ones(x.size, bool)
            for _ in range(10):
                s = np.std(x[keep])
                keep = np.abs(x - np.mean(x[keep])) < 3 * s
            # a clipped Gaussian's std is 0.9866 of the true one; a difference has 2 sigma^2
            sig[key + (p,)] = np.std(x[keep]) / 0.9866 / np.sqrt(2)
            wts[key + (p,)] = (wsp[rows, :, p][~f], sig[key + (p,)])
    return sig, wts


@pytest.mark.realdata
def test_real_evla_empirical_noise_and_error(evla):
    from xstack.schema import iter_partitions, open_store

    ms, store = evla
    sig, wts = _casacore_sigma(ms)
    (_, ds), = list(iter_partitions(open_store(store)))
    pols = [str(p) for p in ds["polarization"].values]
    pm = np.isin(pols, ["RR", "LL"])
    var, n, invw = _scatter.pair_variance(ds["VISIBILITY"].values, ds["WEIGHT"].values,
                                          ds["FLAG"].values, pol_mask=pm)
    ours = np.sqrt(var[:, pm][np.isfinite(var[:, pm])])
    theirs = np.array(list(sig.values()))
    assert ours.size == theirs.size == 2 * 153
    assert np.median(ours) == pytest.approx(np.median(theirs), rel=0.2)
    # the weights claim ~2.5 Jy per part; the data scatter by a few mJy
    assert 2.0 < np.sqrt(np.nanmedian(invw[:, pm])) < 3.0
    assert np.median(ours) < 0.02

    # one position at the phase center, no weighting, no beam: P = 1, so the honest error is
    # sqrt(sum w^2 sigma^2) / sum w with the casacore sigma of each visibility's baseline
    ra0, dec0 = (float(x) for x in ds.attrs["phase_center"])
    one = Table({"ra": [np.degrees(ra0)], "dec": [np.degrees(dec0)]})
    with pytest.warns(UserWarning, match="errors='empirical'"):
        res = stack_uv(store, one, weighting="none", primary_beam="none")
    num = sum(np.sum(w.astype(np.float64) ** 2) * s**2 for w, s in wts.values())
    den = sum(np.sum(w.astype(np.float64)) for w, _ in wts.values())
    assert res.n_visibilities == sum(w.size for w, _ in wts.values())
    assert res.flux_err_empirical_jy == pytest.approx(np.sqrt(num) / den, rel=0.2)
    assert res.noise_estimate["own"] == res.n_visibilities

    # a 20-position stack (within 20" of the center): orders of magnitude apart
    rng = np.random.default_rng(0)
    l, m = rng.uniform(-1e-4, 1e-4, (2, 20))
    ra, dec = lm_to_radec(l, m, ra0, dec0)
    cat = Table({"ra": np.degrees(ra), "dec": np.degrees(dec)})
    with pytest.warns(UserWarning, match="errors='empirical'"):
        res20 = stack_uv(store, cat)
    assert res20.n_positions == 20
    assert res20.flux_err_empirical_jy < res20.flux_err_jy / 100
    assert res20.weight_scale < 1e-4


def test_pooled_scale_memory_is_bounded_by_the_pair_cap_not_the_block():
    """The pooled factor keeps every k-th pair (at most MAX_PAIRS * 16), so its memory does
    not grow with the block: it used to store every pair of the block (the block's size in
    float64 pairs, ~1x a complex64 chunk) before subsampling. Same factor to the bit as the
    every-pair computation (the plain-numpy twin below, same pairs, same medians)."""
    import tracemalloc

    from xstack._scatter import _MAD_BIAS, MAD_TO_SIGMA, MAX_PAIRS, pooled_weight_scale

    rng = np.random.default_rng(12)
    shape = (120, 351, 10, 2)
    vis = (rng.normal(size=shape) + 1j * rng.normal(size=shape)).astype(np.complex64) * 3.0
    w = rng.uniform(0.5, 2.0, shape).astype(np.float32)
    f = rng.random(shape) < 0.05
    scale, n = pooled_weight_scale(vis, w, f)
    big = np.tile(vis, (5, 1, 1, 1))  # 34 MB: the pair cap, not the block, sets the memory
    tracemalloc.start()
    try:
        pooled_weight_scale(big, np.tile(w, (5, 1, 1, 1)), np.tile(f, (5, 1, 1, 1)))
        tracemalloc.reset_peak()
        pooled_weight_scale(big, 1.0, False)  # scalars broadcast: no weight/flag copies
        peak = tracemalloc.get_traced_memory()[1] - tracemalloc.get_traced_memory()[0]
    finally:
        tracemalloc.stop()
    assert peak < 0.15 * big.nbytes, (peak, big.nbytes)
    # plain numpy: every disjoint neighbour pair along the channels, per baseline/correlation
    zr, zi = [], []
    for b in range(shape[1]):
        for p in range(shape[3]):
            for t in range(shape[0]):
                prev = None
                for c in range(shape[2]):
                    if f[t, b, c, p] or not w[t, b, c, p] > 0:
                        prev = None
                        continue
                    cur = (complex(vis[t, b, c, p]), 1.0 / float(w[t, b, c, p]))
                    if prev is None:
                        prev = cur
                        continue
                    norm = 1.0 / np.sqrt(prev[1] + cur[1])
                    zr.append((cur[0].real - prev[0].real) * norm)
                    zi.append((cur[0].imag - prev[0].imag) * norm)
                    prev = None
    assert n == len(zr)
    step = -(-n // (16 * MAX_PAIRS))
    xr, xi = np.array(zr[::step]), np.array(zi[::step])
    dev = np.concatenate([np.abs(xr - np.median(xr)), np.abs(xi - np.median(xi))])
    s = MAD_TO_SIGMA * np.median(dev)
    assert scale == pytest.approx(s * s * dev.size / (dev.size - _MAD_BIAS), rel=1e-12)
