"""The simulator end to end: eq. 1 against independent numpy, primary beam, noise statistics,
opt-in steps (counted, not timed), determinism across chunkings, files written."""

from __future__ import annotations

import math

import dask
import numpy as np
import pytest
from _sim_helpers import direct_eq1
from astropy.table import Table
from scipy import stats

from xstack.beams import standard_beam
from xstack.coords import radec_to_lmn
from xstack.errors import XstackError
from xstack.schema import open_store
from xstack.sim import kernels
from xstack.sim.scene import PAPER_FIELD_CENTER
from xstack.sim.simulate import simulate, simulate_partitions

RA0, DEC0 = PAPER_FIELD_CENTER


def _scene(populations, **kw):
    base = {
        "name": "t",
        "array": {"config": "alma.cycle1.2"},
        "observation": {"hour_angle": [-1.0, 1.0], "integration": 6.0, "time_per_pointing": 30.0},
        "spectral": {"center": 230e9, "bandwidth": 4e9, "channels": 8,
                     "polarizations": ["XX", "XY", "YX", "YY"]},
        "pointings": {"mode": "single", "center": [RA0, DEC0]},
        "effects": {},
        "visibility_dtype": "complex128",
        "populations": populations,
    }
    for k, v in kw.items():
        if isinstance(v, dict) and k in base:
            base[k] = {**base[k], **v}
        else:
            base[k] = v
    return base


def _pop(name, ra, dec, flux, fwhm=None):
    shape = {"kind": "gaussian", "fwhm_arcsec": [fwhm]} if fwhm else {"kind": "point"}
    return {"name": name, "count": len(ra), "flux": {"kind": "fixed", "value": flux},
            "positions": {"kind": "list", "ra": list(ra), "dec": list(dec)}, "shape": shape}


def _first(parts):
    return next(iter(parts.values()))


def test_point_source_at_phase_center_is_constant_and_cheap():
    scene = _scene([_pop("c", [RA0], [DEC0], 2e-3)])
    with kernels.record_steps() as steps:
        parts, cats = simulate_partitions(scene, seed=1)
        ds = _first(parts).compute()
    vis = ds.VISIBILITY.values
    assert np.all(vis[..., [0, 3]] == 2e-3) and np.all(vis[..., [1, 2]] == 0)
    assert not ds.FLAG.values.any() and np.all(ds.WEIGHT.values == 1)
    # no phasors, no w-term, no Gaussian, no beam, no random numbers
    assert set(steps) == {"constant"}


def test_offset_sources_match_independent_eq1():
    rng = np.random.default_rng(7)
    ra = RA0 + rng.uniform(-8, 8, 6) / 3600 / math.cos(math.radians(DEC0))
    dec = DEC0 + rng.uniform(-8, 8, 6) / 3600
    scene = _scene([_pop("a", ra[:3], dec[:3], 1e-3), _pop("b", ra[3:], dec[3:], 3e-3, 1.5)],
                   effects={"w_term": True, "primary_beam": "auto"})
    with kernels.record_steps() as steps:
        parts, cats = simulate_partitions(scene)
        ds = _first(parts).compute()
    assert {"phase", "w_term", "gaussian", "attenuation"} <= set(steps)
    freq = ds.frequency.values
    uvw = ds.UVW.values.reshape(-1, 3)
    beam = standard_beam("ALMA", 12.0)
    ref = 0
    for table in cats.values():
        r, d = np.radians(table["ra"]), np.radians(table["dec"])
        l, m, _, nm1 = radec_to_lmn(r, d, math.radians(RA0), math.radians(DEC0))
        sep = np.hypot(l, m)  # small field: fine as the independent PB argument
        sep = np.arcsin(sep)
        att = beam(sep[:, None], freq[None, :])
        fwhm = np.radians(np.asarray(table["fwhm_arcsec"]) / 3600) if "fwhm_arcsec" in table.colnames \
            else None
        ref = ref + direct_eq1(uvw, freq, l, m, nm1, table["flux"], att, fwhm)
    got = ds.VISIBILITY.values[..., 0].reshape(ref.shape)
    total = 3 * 1e-3 + 3 * 3e-3
    assert np.abs(got - ref).max() / total < 1e-9
    assert np.array_equal(ds.VISIBILITY.values[..., 0], ds.VISIBILITY.values[..., 3])


def test_primary_beam_attenuation_at_offsets_and_channels():
    """Pointings at 0, 8, 15 and 22 arcsec from one source: |V| = S A(theta, nu)."""
    offs = np.array([0.0, 8.0, 15.0, 22.0])
    decs = DEC0 + offs / 3600
    scene = _scene([_pop("s", [RA0], [DEC0], 1.0)],
                   pointings={"mode": "list", "positions": [[RA0, d] for d in decs]},
                   effects={"primary_beam": "auto"})
    parts, _ = simulate_partitions(scene)
    beam = standard_beam("ALMA", 12.0)
    assert len(parts) == 4
    for p, ds in enumerate(parts.values()):
        amp = np.abs(ds.VISIBILITY.values[..., 0])  # (time, bl, chan)
        expect = beam(np.radians(offs[p] / 3600), ds.frequency.values)
        assert np.allclose(amp, expect[None, None, :], rtol=1e-9, atol=0)
        if p:
            assert expect[-1] < expect[0] < 1  # narrower beam at the higher channels


@pytest.mark.parametrize("model", ["airy", "gaussian"])
def test_airy_and_gaussian_beams_against_their_formulas(model):
    """effects.primary_beam = airy | gaussian (12 m ALMA dishes), pointings 0-15" from the
    source: |V| equals the textbook power pattern in every channel."""
    from scipy.special import j1

    offs = np.array([0.0, 5.0, 10.0, 15.0])
    scene = _scene([_pop("s", [RA0], [DEC0], 1.0)],
                   pointings={"mode": "list", "positions": [[RA0, DEC0 + d / 3600] for d in offs]},
                   effects={"primary_beam": model, "pb_cutoff": 0.01})
    parts, _ = simulate_partitions(scene)
    for p, ds in enumerate(parts.values()):
        lam = 299_792_458.0 / ds.frequency.values
        theta = np.radians(offs[p] / 3600)
        if model == "airy":
            x = np.pi * 12.0 * np.sin(theta) / lam
            expect = np.ones_like(x) if theta == 0 else (2 * j1(x) / x) ** 2
        else:
            expect = np.exp(-4 * np.log(2) * (theta / (1.13 * lam / 12.0)) ** 2)
        amp = np.abs(ds.VISIBILITY.values[..., 0])
        np.testing.assert_allclose(amp, np.broadcast_to(expect, amp.shape), rtol=1e-9, atol=0)
        if p:
            assert 0.05 < expect[-1] < expect[0] < 1


def test_noise_has_the_requested_sigma():
    sigma = 0.37
    scene = _scene([], effects={"noise": {"sigma": sigma}})
    with kernels.record_steps() as steps:
        ds = _first(simulate_partitions(scene, seed=11)[0]).compute()
    assert steps["noise"] > 0
    z = ds.VISIBILITY.values.ravel() / sigma
    x = np.concatenate([z.real, z.imag])
    chi2 = float(np.sum(x**2))
    dof = x.size
    # two-sided chi-square test of the variance, and normality of the draws
    p = 2 * min(stats.chi2.cdf(chi2, dof), stats.chi2.sf(chi2, dof))
    assert p > 1e-3, (chi2, dof)
    assert stats.kstest(x[:20000], "norm").pvalue > 1e-3
    assert np.allclose(ds.WEIGHT.values, 1 / sigma**2, rtol=1e-6)
    # a wrong sigma is detected by the same test
    chi2_wrong = float(np.sum((x * sigma / (1.05 * sigma)) ** 2))
    assert stats.chi2.cdf(chi2_wrong, dof) < 1e-3


def test_noise_from_sefd():
    scene = _scene([], effects={"noise": {"sefd": 5000.0, "efficiency": 0.9}})
    ds = _first(simulate_partitions(scene)[0])
    width = float(ds.channel_width.values[0])
    expect = 5000.0 / (0.9 * math.sqrt(2 * width * 6.0))
    assert np.allclose(1 / np.sqrt(ds.WEIGHT.values[0, 0]), expect, rtol=1e-6)
    assert ds.attrs["noise_sigma_jy"] == pytest.approx(expect)


def test_noiseless_scene_draws_no_random_numbers_and_no_w_term():
    scene = _scene([_pop("a", [RA0 + 0.002], [DEC0], 1e-3)])
    with kernels.record_steps() as steps:
        _first(simulate_partitions(scene)[0]).VISIBILITY.compute()
    assert "noise" not in steps and "flag_random" not in steps and "w_term" not in steps
    assert "gaussian" not in steps and "attenuation" not in steps and steps["phase"] > 0


@pytest.mark.parametrize("chunk, bl_chunk", [(1, 0), (2, 100), (5, 37)])
def test_same_seed_same_bits_whatever_the_chunking(chunk, bl_chunk):
    pops = [{"name": "r", "count": 20, "flux": {"kind": "power_law", "index": -2.0,
                                                 "s_min": 1e-4, "s_max": 1e-2},
             "positions": {"kind": "disc", "radius_arcsec": 15.0}}]
    eff = {"noise": {"sigma": 0.1}, "flagging": {"random_fraction": 0.1}, "w_term": True,
           "primary_beam": "auto"}
    ref = _first(simulate_partitions(_scene(pops, effects=eff), seed=5)[0]).compute(
        scheduler="synchronous")
    other = _scene(pops, effects=eff, time_chunk=chunk, baseline_chunk=bl_chunk)
    ds = _first(simulate_partitions(other, seed=5)[0])
    nb = math.ceil(496 / bl_chunk) if bl_chunk else 1
    assert ds.VISIBILITY.data.npartitions == math.ceil(5 / chunk) * nb
    with dask.config.set(scheduler="threads", num_workers=2):
        got = ds.compute()
    for var in ("VISIBILITY", "FLAG", "WEIGHT", "UVW"):
        assert np.array_equal(got[var].values, ref[var].values), var
    diff = _first(simulate_partitions(_scene(pops, effects=eff), seed=6)[0]).VISIBILITY.values
    assert not np.array_equal(diff, ref.VISIBILITY.values)
    flagged = ref.FLAG.values.mean()
    assert 0.08 < flagged < 0.12


def test_shadowing_flags_the_antenna_behind():
    site = np.array([2225142.18, -5440307.37, -2481029.85])
    from xstack.sim.arrays import enu_to_itrf

    pos = enu_to_itrf(np.array([[0, 0, 0], [0, 9.0, 0], [300, 0, 0]], float), site)
    scene = _scene([], array={"positions": pos.tolist(), "diameters": [12.0] * 3,
                              "names": ["A", "B", "C"], "telescope": "ALMA"},
                   effects={"flagging": {"shadowing": True}})
    with kernels.record_steps() as steps:
        ds = _first(simulate_partitions(scene)[0]).compute()
    assert steps["flag_shadow"] > 0
    flag = ds.FLAG.values.all(axis=(2, 3))  # (time, baseline): AB, AC, BC
    # a source at dec -30 seen from ALMA is north of zenith-ish but low enough in the north
    # that one of A/B (9 m apart north-south, 12 m dishes) always shadows the other
    assert flag[:, 0].all() and (flag[:, 1].all() or flag[:, 2].all())
    assert not (flag[:, 1] & flag[:, 2]).any()


def test_simulate_writes_store_and_catalogs(tmp_path):
    pops = [_pop("bright", [RA0 + 0.001], [DEC0], "5mJy"),
            {"name": "targets", "count": 7, "flux": {"kind": "fixed", "value": "1mJy"},
             "positions": {"kind": "disc", "radius_arcsec": 10.0},
             "shape": {"kind": "gaussian", "fwhm_arcsec": [0.5, 2.0]}}]
    out = tmp_path / "sim.zarr"
    res = simulate(_scene(pops, effects={"noise": {"sigma": 0.1}}), out, seed=3)
    assert res.store == out and res.steps_run == {"model", "phase", "extent", "noise"}
    tree = open_store(out)
    ds = tree["spw0_field0"].to_dataset()
    assert ds.sizes["polarization"] == 4 and ds.attrs["field_name"] == "pointing0"
    assert res.catalog_paths == {"bright": tmp_path / "sim.bright.ecsv",
                                 "targets": tmp_path / "sim.targets.ecsv"}
    t = Table.read(res.catalog_paths["targets"])
    assert t.colnames == ["ra", "dec", "flux", "fwhm_arcsec", "pointing"]
    assert len(t) == 7 and np.all((t["fwhm_arcsec"] >= 0.5) & (t["fwhm_arcsec"] <= 2.0))
    assert "fwhm_arcsec" not in Table.read(res.catalog_paths["bright"]).colnames
    assert tree.attrs["simulation"]["seed"] == 3
    # existing outputs are refused without overwrite, and nothing changes
    with pytest.raises(XstackError, match="exists"):
        simulate(_scene(pops), out, seed=4)
    again = simulate(_scene(pops, effects={"noise": {"sigma": 0.1}}), out, seed=3, overwrite=True)
    assert np.array_equal(open_store(again.store)["spw0_field0"].VISIBILITY.values,
                          ds.VISIBILITY.values)


def test_existing_catalog_blocks_before_writing(tmp_path):
    (tmp_path / "x.p.ecsv").write_text("occupied")
    with pytest.raises(XstackError, match="exists"):
        simulate(_scene([_pop("p", [RA0], [DEC0], 1e-3)]), tmp_path / "x.zarr")
    assert not (tmp_path / "x.zarr").exists()


def test_sources_outside_every_pointing_are_refused():
    scene = _scene([_pop("far", [RA0], [DEC0 + 0.05], 1e-3)])
    with pytest.raises(XstackError, match=r"populations\[0\].positions.*outside every pointing"):
        simulate_partitions(scene)


def test_gaussian_source_matches_numerical_fourier_transform():
    """Independent truth for an extended source: the visibilities of a circular Gaussian
    (FWHM 2") 3.6" from the phase center equal a direct numerical Fourier sum over its
    brightness distribution sampled in the (l, m) plane (no analytic transform used)."""
    ra = RA0 + 3.0 / 3600 / math.cos(math.radians(DEC0))
    dec = DEC0 + 2.0 / 3600
    scene = _scene([_pop("g", [ra], [dec], 1.0, fwhm=2.0)],
                   spectral={"channels": 3, "polarizations": ["XX", "YY"]},
                   observation={"time_per_pointing": 12.0})
    ds = _first(simulate_partitions(scene)[0]).compute()
    got = ds.VISIBILITY.values[..., 0].reshape(-1, ds.sizes["frequency"])  # (rows, chan)
    uvw = ds.UVW.values.reshape(-1, 3)
    l0, m0, _, _ = radec_to_lmn(math.radians(ra), math.radians(dec), math.radians(RA0),
                                math.radians(DEC0))
    sigma = math.radians(2.0 / 3600) / (2 * math.sqrt(2 * math.log(2)))
    h = math.radians(0.02 / 3600)  # << 1/(u/lambda)max ~ 0.27": no aliasing
    x = np.arange(-8 * sigma, 8 * sigma + h / 2, h)
    g = np.exp(-x**2 / (2 * sigma**2)) / (math.sqrt(2 * math.pi) * sigma) * h
    ref = np.empty_like(got)
    for c, f in enumerate(ds.frequency.values):
        lam = 299_792_458.0 / f
        # brightness = g(l - l0) g(m - m0), summed on absolute l, m grids: separable sums
        fl = np.exp(2j * np.pi * np.outer(uvw[:, 0], l0 + x) / lam) @ g
        fm = np.exp(2j * np.pi * np.outer(uvw[:, 1], m0 + x) / lam) @ g
        ref[:, c] = fl * fm
    assert np.abs(ref).min() < 0.5 and np.abs(ref).max() > 0.9  # resolved on long baselines
    assert np.abs(got - ref).max() < 1e-9


def test_noise_from_system_temperature():
    """sigma = 2 k Tsys / (eta_a A) / (eta_c sqrt(2 dnu tau)), written out independently."""
    from astropy import constants as const

    tsys, eta_a, eta_c = 90.0, 0.71, 0.88
    scene = _scene([], effects={"noise": {"tsys": tsys, "aperture_efficiency": eta_a,
                                          "efficiency": eta_c}},
                   spectral={"polarizations": ["XX", "YY"]})
    ds = _first(simulate_partitions(scene, seed=4)[0]).compute()
    area = math.pi * 6.0**2  # ALMA 12 m dishes
    sefd_jy = 2 * const.k_B.value * tsys / (eta_a * area) / 1e-26
    dnu = 4e9 / 8
    sigma = sefd_jy / (eta_c * math.sqrt(2 * dnu * 6.0))
    assert 0.02 < sigma < 0.1  # SEFD ~3100 Jy: ~45 mJy per part in 500 MHz and 6 s
    assert np.allclose(1 / np.sqrt(ds.WEIGHT.values), sigma, rtol=1e-6)
    z = ds.VISIBILITY.values.ravel() / sigma
    x = np.concatenate([z.real, z.imag])
    chi2 = float(np.sum(x**2))
    assert 2 * min(stats.chi2.cdf(chi2, x.size), stats.chi2.sf(chi2, x.size)) > 1e-3


_RNG_NAMES = ("Generator", "default_rng", "PCG64", "PCG64DXSM", "MT19937", "Philox", "SFC64",
              "SeedSequence", "RandomState", "normal", "standard_normal", "uniform", "random",
              "rand", "randn", "random_sample", "randint", "choice", "seed")


def _trace_rng(monkeypatch):
    """Count every way numpy can make random numbers (bit generators, legacy functions)."""
    calls = []
    for name in _RNG_NAMES:
        real = getattr(np.random, name)

        def traced(*args, _real=real, _name=name, **kwargs):
            calls.append(_name)
            return _real(*args, **kwargs)

        monkeypatch.setattr(np.random, name, traced)
    return calls


@pytest.mark.parametrize("effects, random_expected", [
    ({"w_term": True, "primary_beam": "auto", "flagging": {"shadowing": True}}, False),
    ({"noise": {"sigma": 0.1}}, True),
    ({"flagging": {"random_fraction": 0.1}}, True),
])
def test_random_numbers_drawn_only_for_noise_and_random_flags(monkeypatch, effects,
                                                              random_expected):
    """Call tracing of numpy's random API while the data are computed: a noiseless scene
    (even with every deterministic effect on) never touches it."""
    pops = [_pop("a", [RA0 + 0.002], [DEC0], 1e-3, fwhm=1.0)]
    ds = _first(simulate_partitions(_scene(pops, effects=effects), seed=2)[0])
    calls = _trace_rng(monkeypatch)
    ds.compute(scheduler="threads")
    assert bool(calls) == random_expected, calls[:5]


@pytest.mark.slow
def test_same_bits_on_a_distributed_cluster(tmp_path):
    """simulate() written through a dask.distributed LocalCluster (2 worker processes, other
    chunks) equals the single-threaded in-memory result bit for bit."""
    distributed = pytest.importorskip("dask.distributed")
    pops = [{"name": "r", "count": 15, "flux": {"kind": "power_law", "index": -2.0,
                                                 "s_min": 1e-4, "s_max": 1e-2},
             "positions": {"kind": "disc", "radius_arcsec": 15.0},
             "shape": {"kind": "gaussian", "fwhm_arcsec": [0.5, 2.0]}}]
    eff = {"noise": {"sigma": 0.1}, "flagging": {"random_fraction": 0.1}, "w_term": True,
           "primary_beam": "auto"}
    ref = _first(simulate_partitions(_scene(pops, effects=eff), seed=8)[0]).compute(
        scheduler="synchronous")
    scene = _scene(pops, effects=eff, time_chunk=2, baseline_chunk=70)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client:
        with distributed.get_task_stream(client) as stream:
            res = simulate(scene, tmp_path / "d.zarr", seed=8)
        # the chunks really were computed on both worker processes
        assert len({task["worker"] for task in stream.data}) == 2
    got = open_store(res.store)["spw0_field0"].to_dataset()
    assert got.VISIBILITY.data.chunksize[:2] == (2, 70)
    for var in ("VISIBILITY", "FLAG", "WEIGHT", "UVW"):
        assert np.array_equal(got[var].values, ref[var].values), var


def test_elevation_limit_flags_each_antenna_below_it_as_astropy_sees_it():
    """Per-antenna elevation against astropy's AltAz (no refraction) at every integration of
    the VLA-A track of the paper's presets (HA -4.8..4.8 h at dec -30: below 10 deg at both
    ends); a baseline is flagged when either antenna is below the limit."""
    import astropy.units as un
    from astropy.coordinates import AltAz, EarthLocation, SkyCoord
    from astropy.time import Time

    scene = _scene([_pop("c", [RA0 + 0.01], [DEC0], 1e-3)],
                   array={"config": "vla.a"},
                   observation={"hour_angle": [-4.8, 4.8], "integration": 300.0,
                                "time_per_pointing": 33840.0},
                   spectral={"center": 1.4e9, "bandwidth": 25e6, "channels": 1,
                             "polarizations": ["RR", "LL"]},
                   effects={"flagging": {"elevation_limit_deg": 10.0}})
    with kernels.record_steps() as steps:
        ds = _first(simulate_partitions(scene)[0]).compute()
    assert steps["flag_elevation"] > 0
    flag = ds.FLAG.values
    assert (flag == flag[..., :1, :1]).all()  # whole rows: every channel and polarization
    flag = flag[:, :, 0, 0]
    pos = ds.ANTENNA_POSITION.values
    t = Time(ds.time.values / 86400.0, format="mjd", scale="utc")
    src = SkyCoord(RA0 * un.deg, DEC0 * un.deg)
    alt = np.stack([src.transform_to(AltAz(obstime=t, location=EarthLocation.from_geocentric(
        *p, unit="m"))).alt.deg for p in pos], axis=1)  # (time, antenna)
    a1, a2 = ds.baseline_antenna1_name.values, ds.baseline_antenna2_name.values
    names = list(ds.antenna_name.values)
    i1 = np.array([names.index(a) for a in a1])
    i2 = np.array([names.index(a) for a in a2])
    low = np.minimum(alt[:, i1], alt[:, i2])
    clear = np.abs(low - 10.0) > 0.05  # astropy adds aberration, polar motion: 0.02 deg
    np.testing.assert_array_equal(flag[clear], (low < 10.0)[clear])
    assert 0.2 < flag.mean() < 0.35 and flag[0].all() and not flag[flag.shape[0] // 2].any()


def test_elevation_limit_is_checked():
    with pytest.raises(XstackError, match="elevation_limit_deg"):
        _first(simulate_partitions(_scene([], effects={
            "flagging": {"elevation_limit_deg": 95.0}}))[0])


@pytest.mark.parametrize("flagging, bias", [(None, True), ("presets", False)])
def test_low_elevation_baselines_bias_a_stack_at_random_positions(flagging, bias):
    """Why the presets flag like CASA's simulator. On the VLA-A track of the paper (HA
    -4.8..4.8 h at dec -30), near the horizon baselines foreshorten to a few metres, where every
    source of the field adds in phase: the mean of a stack over positions uniform in the
    field's box (the short-baseline visibilities times the box's characteristic function,
    computed here with numpy from the stored data) is then 1.6-1.9e-4 of the field's flux.
    With the presets' elevation limit and shadowing it is 1e-5 or less (sources in random
    places add incoherently) and no unflagged baseline is shorter than a dish."""
    from xstack.sim.presets import SIMULATOR_FLAGGING

    effects = {"w_term": True}
    if flagging == "presets":
        effects["flagging"] = dict(SIMULATOR_FLAGGING)
    scene = _scene([{"name": "bright", "count": 50, "flux": {"kind": "fixed", "value": 0.01},
                     "positions": {"kind": "box", "size_arcsec": [1800, 1800]}}],
                   array={"config": "vla.a"},
                   observation={"hour_angle": [-4.8, 4.8], "integration": 120.0,
                                "time_per_pointing": 33840.0},
                   spectral={"center": 1.4e9, "bandwidth": 25e6, "channels": 1,
                             "polarizations": ["RR", "LL"]},
                   effects=effects, visibility_dtype="complex64")
    ds = _first(simulate_partitions(scene, seed=1)[0]).compute()
    ok = ~ds.FLAG.values[:, :, 0, 0]
    uvw = ds.UVW.values / (299_792_458.0 / ds.frequency.values[0])  # wavelengths
    half = math.radians(900 / 3600)  # half the box (rad)
    box = np.sinc(2 * uvw[..., 0] * half) * np.sinc(2 * uvw[..., 1] * half)
    short = ok & (np.hypot(uvw[..., 0], uvw[..., 1]) < 6e3)  # the 0-6 klambda bin
    vis = ds.VISIBILITY.values[:, :, 0, 0].real
    mean_over_box = float((box[short] * vis[short]).sum() / short.sum()) / (50 * 0.01)
    shortest = float(np.hypot(ds.UVW.values[..., 0], ds.UVW.values[..., 1])[ok].min())
    if bias:
        assert mean_over_box > 1e-4 and shortest < 25.0
    else:
        assert abs(mean_over_box) < 3e-5 and shortest > 25.0
