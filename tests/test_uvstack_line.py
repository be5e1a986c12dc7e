"""The uv-domain line stack (xstack.uvstack.line): truth from a plain-numpy stacker, lines
injected with numpy (and written with python-casacore), analytic regridding."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from _uvstack_helpers import VLA_CENTER, antenna_layout, earth_rotation_uvw
from astropy.table import Table
from scipy.optimize import curve_fit
from scipy.special import erf

from xstack.coords import SPEED_OF_LIGHT, angular_separation, radec_to_lmn
from xstack.schema import new_partition
from xstack.spectral import (
    SPEED_OF_LIGHT_KMS,
    line_centres_hz,
    observed_line_centre,
    overlap_lengths,
    velocity_edges,
)
from xstack.uvstack import line_kernels
from xstack.uvstack.line import stack_lines
from xstack.uvstack.line_reference import ReferencePartition, reference_line_stack

HI = 1_420_405_751.768
ITRF_VLA = np.array([-1601185.4, -5041977.5, 3554875.9])


def _partition(*, n_ant=6, n_time=8, freq0=1.30e9, dfreq=100e3, n_chan=48, center=VLA_CENTER,
               seed=0, field_id=0, frame=None, vis=None, sigma=1.0, hours=4.0):
    """A partition (time, baseline, channel, RR/LL): ``vis(uvw, freq)`` -> (t, b, c) noiseless
    visibilities (default none) plus Gaussian noise ``sigma`` (WEIGHT random about 1/sigma^2)."""
    rng = np.random.default_rng(seed)
    enu = antenna_layout(n_ant, 1500.0, rng)
    uvw, a1, a2 = earth_rotation_uvw(enu, n_time, center[1], hours=hours)
    freq = freq0 + dfreq * np.arange(n_chan)
    shape = uvw.shape[:2] + (n_chan, 2)
    v = np.zeros(shape, dtype=np.complex128)
    if vis is not None:
        v += vis(uvw, freq)[..., None]
    if sigma > 0:
        v += sigma * (rng.normal(size=shape) + 1j * rng.normal(size=shape))
        weight = rng.uniform(0.5, 2.0, size=shape) / sigma**2
    else:
        weight = rng.uniform(0.5, 2.0, size=shape)
    ds = new_partition(
        visibility=v, weight=weight.astype(np.float32), flag=np.zeros(shape, bool), uvw=uvw,
        time=5.0e9 + 600.0 * np.arange(n_time), antenna1=a1, antenna2=a2,
        antenna_names=[f"ea{i:02d}" for i in range(n_ant)], antenna_positions=enu + ITRF_VLA,
        dish_diameters=np.full(n_ant, 25.0), frequency=freq,
        channel_width=np.full(n_chan, dfreq), polarization=["RR", "LL"], phase_center=center,
        telescope_name="VLA", integration_time=600.0, field_id=field_id,
        field_name=f"field{field_id}")
    if frame is not None:
        ds["frequency"].attrs["observer"] = frame
    return ds


def _gaussian_line(flux_jy_kms, sigma_kms):
    """Channel-averaged flux density (Jy) of a Gaussian line over velocity intervals."""
    def density(v_lo, v_hi):
        cdf = 0.5 * (erf(v_hi / (np.sqrt(2) * sigma_kms)) - erf(v_lo / (np.sqrt(2) * sigma_kms)))
        return flux_jy_kms * cdf / (v_hi - v_lo)
    return density


def _line_vis(targets, center, profile, ratio=None):
    """vis(uvw, freq) of point sources with line spectra: targets = [(ra, dec, centre_hz)]
    radians/Hz; ``ratio`` (t,) nu_frame / nu_data per integration (None: 1)."""
    def vis(uvw, freq):
        nt = uvw.shape[0]
        r = np.ones(nt) if ratio is None else np.asarray(ratio)
        width = freq[1] - freq[0]
        out = np.zeros(uvw.shape[:2] + (freq.size,), dtype=np.complex128)
        for ra, dec, nu_c in targets:
            l, m, _n, n1 = radec_to_lmn(np.array([ra]), np.array([dec]), *center)
            d = uvw @ np.array([l[0], m[0], n1[0]])  # (t, b)
            for c, nu in enumerate(freq):
                # the channel's velocity interval in the line's frame, per integration
                v_lo = SPEED_OF_LIGHT_KMS * (1 - r * (nu + width / 2) / nu_c)
                v_hi = SPEED_OF_LIGHT_KMS * (1 - r * (nu - width / 2) / nu_c)
                s = profile(v_lo, v_hi)[:, None]
                out[..., c] += s * np.exp(2j * np.pi * d * nu / SPEED_OF_LIGHT)
        return out
    return vis


def _fit_gaussian(result, window=None):
    """(centre, sigma, integral) and errors of a Gaussian fitted with the full covariance."""
    v, s, cov = result.velocity_kms, result.flux_jy, result.flux_cov_jy2
    ok = np.isfinite(s) if window is None else np.isfinite(s) & (np.abs(v) < window)
    dv = result.velocity_edges_kms[1] - result.velocity_edges_kms[0]

    def model(x, a, mu, sig):
        lo, hi = x - dv / 2, x + dv / 2
        return a * 0.5 * (erf((hi - mu) / (np.sqrt(2) * sig))
                          - erf((lo - mu) / (np.sqrt(2) * sig))) / dv

    p, pc = curve_fit(model, v[ok], s[ok], p0=[s[ok].max() * 100, 0.0, 60.0],
                      sigma=cov[np.ix_(ok, ok)], absolute_sigma=True)
    return p, np.sqrt(np.diag(pc))


def _reference_parts(dss, tab, rest_hz, *, weighting, beam, ratios, uvmin=None):
    """ReferencePartition of each partition, W_k and A_k from xstack.beams directly."""
    from xstack.beams import standard_beam

    ra = np.radians(np.asarray(tab["ra"], dtype=float))
    dec = np.radians(np.asarray(tab["dec"], dtype=float))
    centres = observed_line_centre(rest_hz, np.asarray(tab["z"], dtype=float))
    parts = []
    for ds, ratio in zip(dss, ratios):
        ra0, dec0 = ds.attrs["phase_center"]
        freq = ds["frequency"].values
        l, m, _n, n1 = radec_to_lmn(ra, dec, ra0, dec0)
        if beam == "none":
            att = np.ones((ra.size, freq.size))
            att_ref = np.ones(ra.size)
        else:
            b = standard_beam("VLA", 25.0)
            theta = angular_separation(ra0, dec0, ra, dec)
            att = b.main_lobe(theta[:, None], freq[None, :])
            att_ref = b.main_lobe(theta[:, None], np.array([[freq.mean()]]))[:, 0]
        wk = np.ones(ra.size) if weighting == "none" else att_ref**2
        uvw = ds["UVW"].values
        uv_mask = None
        if uvmin is not None:
            q = np.hypot(uvw[..., 0], uvw[..., 1])
            uv_mask = np.repeat((q >= uvmin)[..., None], freq.size, axis=-1)
        parts.append(ReferencePartition(
            vis=ds["VISIBILITY"].values, weight=ds["WEIGHT"].values, flag=ds["FLAG"].values,
            uvw=uvw, ratio=ratio, frequency=freq, width=ds["channel_width"].values, l=l, m=m,
            n1=n1, centre_hz=centres, wk=wk, inv_att=1.0 / att,
            pol_mask=np.array([True, True]), uv_mask=uv_mask))
    return parts


def _damage(ds, seed):
    """Flag rows and channels (NaN under some flags), zero some weights, NaN some data."""
    rng = np.random.default_rng(seed)
    v = ds["VISIBILITY"].values.copy()
    w = ds["WEIGHT"].values.copy()
    f = rng.uniform(size=v.shape) < 0.1
    f[1, :3] = True  # whole rows
    f[:, :, 5] = True  # a whole channel
    v[f & (rng.uniform(size=v.shape) < 0.5)] = np.nan
    w[rng.uniform(size=w.shape) < 0.05] = 0.0
    nan_unflagged = (rng.uniform(size=v.shape) < 0.01)
    v[nan_unflagged] = np.nan + 1j * np.nan
    return ds.assign(VISIBILITY=(ds["VISIBILITY"].dims, v), WEIGHT=(ds["WEIGHT"].dims, w),
                     FLAG=(ds["FLAG"].dims, f))


# --- against the plain-numpy reference ----------------------------------------------------------

@pytest.mark.parametrize("weighting,beam,uvmin,res", [
    ("none", "none", None, 15.0), ("pb", "auto", 200.0, 40.0)])
def test_matches_numpy_reference(weighting, beam, uvmin, res):
    """Random data, two partitions (LSRK and TOPO), targets at different z (one partly out
    of the band): per-bin flux, error and covariance agree with the reference to 1e-9."""
    from xstack.frames import frame_ratio

    c0 = VLA_CENTER
    c1 = (VLA_CENTER[0] + np.radians(0.05), VLA_CENTER[1] + np.radians(0.02))
    a = _damage(_partition(seed=1, frame="LSRK", center=c0), 11)
    b = _damage(_partition(seed=2, field_id=1, center=c1, n_time=6), 12)  # TOPO
    ra0, dec0 = np.degrees(c0)
    freq_band = 1.30e9 + 100e3 * np.array([5, 20, 35, 46])
    tab = Table({"ra": ra0 + np.array([0.0, 0.03, -0.02, 0.04]),
                 "dec": dec0 + np.array([0.0, 0.01, 0.03, -0.02]),
                 "z": HI / freq_band - 1})
    res_line = stack_lines({"a": a, "b": b}, tab, line_frequency=HI, velocity_resolution=res,
                           velocity_range=(-300, 300), weighting=weighting, primary_beam=beam,
                           uvmin=uvmin)
    rb = frame_ratio(b["time"].values, np.degrees(c1[0]), np.degrees(c1[1]),
                     b["ANTENNA_POSITION"].values.mean(axis=0), to_frame="LSRK")
    assert np.ptp(rb) > 0  # a real Doppler track
    parts = _reference_parts([a, b], tab, HI, weighting=weighting, beam=beam,
                             ratios=[np.ones(a.sizes["time"]), rb], uvmin=uvmin)
    flux, err, cov, ntgt = reference_line_stack(parts, velocity_edges(res, (-300, 300)))
    assert (ntgt == 4).any() and (ntgt < 4).any()  # some targets partly outside
    np.testing.assert_array_equal(np.isnan(res_line.flux_jy), np.isnan(flux))
    ok = np.isfinite(flux)
    scale = np.nanmax(err)
    np.testing.assert_allclose(res_line.flux_jy[ok], flux[ok], rtol=0, atol=1e-9 * scale)
    np.testing.assert_allclose(res_line.flux_err_jy[ok], err[ok], rtol=1e-9)
    np.testing.assert_allclose(res_line.flux_cov_jy2[np.ix_(ok, ok)], cov[np.ix_(ok, ok)],
                               rtol=0, atol=1e-9 * scale**2)
    np.testing.assert_array_equal(res_line.n_targets_per_bin, ntgt)
    assert res_line.n_positions == 4
    assert res_line.to_dict()["frame"] == "lsrk"


def test_sums_bitwise_on_any_thread_count():
    """The kernel's sums are the same to the last bit on 1 and 2 threads."""
    import numba

    ds = _damage(_partition(seed=3, n_time=40, n_ant=8), 5)  # 1120 rows: three sum blocks
    nt, nb, nc, npol = ds["VISIBILITY"].shape
    n = nt * nb
    rng = np.random.default_rng(0)
    ntg = 7
    layout = line_kernels.ChannelLayout(ds["frequency"].values, ds["channel_width"].values)
    args = (ds["VISIBILITY"].values.reshape(n, nc, npol), ds["WEIGHT"].values.reshape(n, nc, npol),
            ds["FLAG"].values.reshape(n, nc, npol), ds["UVW"].values.reshape(n, 3),
            np.repeat(1 + 1e-5 * rng.normal(size=nt), nb), layout,
            rng.normal(scale=1e-3, size=ntg), rng.normal(scale=1e-3, size=ntg),
            rng.normal(scale=1e-7, size=ntg), 1.30e9 + rng.uniform(0, 4.8e6, size=ntg),
            rng.uniform(0.5, 2, size=(ntg, nc)), rng.uniform(0.5, 2, size=ntg),
            velocity_edges(10, (-200, 200)))
    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = line_kernels.line_sums(*args)
        numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
        two = line_kernels.line_sums(*args)
    finally:
        numba.set_num_threads(before)
    assert one.tobytes() == two.tobytes()


# --- an injected line ----------------------------------------------------------------------------

def _ms_with_lines(tmp_path, targets_deg, flux, sigma_kms, noise):
    """An MS (python-casacore, LSRK) with Gaussian lines at the targets; converted."""
    import casacore.tables as pt

    from xstack.io.convert import convert_ms
    from xstack.testing import make_test_ms

    ms = make_test_ms(tmp_path / "line.ms", n_antennas=7, n_times=6, n_channels=256,
                      freq0=1.30e9, channel_width=50e3, telescope="VLA", noise_jy=1.0,
                      flag_fraction=0.0, flag_row_fraction=0.0, pols=("RR", "LL"), seed=4)
    with pt.table(f"{ms}/SPECTRAL_WINDOW", readonly=False, ack=False) as spw:
        spw.putcell("MEAS_FREQ_REF", 0, 1)  # LSRK
        freq = spw.getcell("CHAN_FREQ", 0)
        width = spw.getcell("CHAN_WIDTH", 0)
    with pt.table(f"{ms}/FIELD", ack=False) as fld:
        ra0, dec0 = fld.getcell("PHASE_DIR", 0)[0]
    rng = np.random.default_rng(9)
    profile = _gaussian_line(flux, sigma_kms)
    with pt.table(str(ms), readonly=False, ack=False) as tab:
        uvw = tab.getcol("UVW")
        data = np.zeros((uvw.shape[0], freq.size), dtype=np.complex128)
        for ra, dec, nu_c in targets_deg:
            l, m, _n, n1 = radec_to_lmn(np.radians([ra]), np.radians([dec]), ra0, dec0)
            d = uvw @ np.array([l[0], m[0], n1[0]])
            s = profile(SPEED_OF_LIGHT_KMS * (1 - (freq + width / 2) / nu_c),
                        SPEED_OF_LIGHT_KMS * (1 - (freq - width / 2) / nu_c))
            data += s[None, :] * np.exp(2j * np.pi * d[:, None] * freq[None, :] / SPEED_OF_LIGHT)
        npol = tab.getcell("DATA", 0).shape[1]
        data = np.repeat(data[:, :, None], npol, axis=2)
        data += noise * (rng.normal(size=data.shape) + 1j * rng.normal(size=data.shape))
        tab.putcol("DATA", data.astype(np.complex64))
        w = np.full((uvw.shape[0], npol), 1.0 / noise**2 if noise > 0 else 1.0, np.float32)
        tab.putcol("WEIGHT", w)
        if "WEIGHT_SPECTRUM" in tab.colnames():
            tab.putcol("WEIGHT_SPECTRUM", np.repeat(w[:, None, :], freq.size, axis=1))
        tab.putcol("FLAG", np.zeros(data.shape, bool))
        tab.putcol("FLAG_ROW", np.zeros(uvw.shape[0], bool))
    store = convert_ms(ms, tmp_path / "line.zarr")
    return store, (np.degrees(ra0), np.degrees(dec0)), freq


@pytest.mark.parametrize("noise", [0.0, 0.05])
def test_injected_line_recovered(tmp_path, noise):
    """Gaussian lines (integral 1 Jy km/s, sigma 40 km/s) at 3 targets with their own z:
    the integral over the line and the centre agree with the truth (noiseless: 1e-6). The
    lines are ~1000 km/s apart, so no target's line falls in another's velocity range (its
    sidelobes there would be real signal in the stack, not in this truth)."""
    flux, sig = 1.0, 40.0
    ms_freq0 = 1.30e9
    nus = ms_freq0 + 50e3 * np.array([40.3, 127.9, 216.1])
    offsets = [(0.0, 0.0), (0.004, -0.003), (-0.003, 0.005)]
    # the phase centre of make_test_ms' field (read back below); targets near it
    from xstack.testing._ms import DEFAULT_PHASE_CENTER

    ra0, dec0 = np.degrees(DEFAULT_PHASE_CENTER)
    targets = [(ra0 + a, dec0 + b, nu) for (a, b), nu in zip(offsets, nus)]
    store, (ra_c, dec_c), _freq = _ms_with_lines(tmp_path, targets, flux, sig, noise)
    assert abs(ra_c - ra0) < 1e-9 and abs(dec_c - dec0) < 1e-9
    from xstack.frames import frequency_frame
    from xstack.schema import iter_partitions, open_store

    assert frequency_frame(next(iter_partitions(open_store(store)))[1]) == "LSRK"
    tab = Table({"ra": [t[0] for t in targets], "dec": [t[1] for t in targets],
                 "z": HI / nus - 1})
    res = stack_lines(store, tab, line_frequency="HI", velocity_resolution=20.0,
                      velocity_range=(-300, 300), primary_beam="none", weighting="none")
    dv = 20.0
    assert (res.n_targets_per_bin == 3).all()
    integral = np.sum(res.flux_jy) * dv
    integral_err = dv * np.sqrt(res.flux_cov_jy2.sum())
    centre = np.sum(res.velocity_kms * res.flux_jy) * dv / integral
    if noise == 0:
        # the truth: each target's channel averages, spread over the bins by overlap
        edges = res.velocity_edges_kms
        num = np.zeros(edges.size - 1)
        den = np.zeros(edges.size - 1)
        freq = _freq
        for nu_c in nus:
            vlo = SPEED_OF_LIGHT_KMS * (1 - (freq + 25e3) / nu_c)
            vhi = SPEED_OF_LIGHT_KMS * (1 - (freq - 25e3) / nu_c)
            o = overlap_lengths(np.column_stack([vlo, vhi]), edges)
            num += _gaussian_line(flux, sig)(vlo, vhi) @ o
            den += o.sum(axis=0)
        np.testing.assert_allclose(res.flux_jy, num / den, rtol=0, atol=1e-6 * flux / sig)
        assert integral == pytest.approx(flux, rel=1e-6)
        assert abs(centre) < 0.5
    else:
        assert abs(integral - flux) < 4 * integral_err
        p, perr = _fit_gaussian(res)
        assert abs(p[1]) < 4 * perr[1]
        assert abs(p[2] - sig) < 4 * perr[2]
        assert abs(p[0] - flux) < 4 * perr[0]


# --- a target partly outside the band -----------------------------------------------------------

def test_partly_outside_contributes_only_its_bins():
    """Target B's line sits at the band edge: it counts only in the bins it covers, and the
    bins only A covers are the stack of A alone."""
    ra0, dec0 = np.degrees(VLA_CENTER)
    nu_a = 1.30e9 + 100e3 * 24
    nu_b = 1.30e9 + 100e3 * 2  # ~ -60 km/s of band below, 1000 above
    targets = [(VLA_CENTER[0], VLA_CENTER[1], nu_a),
               (VLA_CENTER[0] + np.radians(0.02), VLA_CENTER[1], nu_b)]
    ds = _partition(seed=5, frame="LSRK", sigma=0.3,
                    vis=_line_vis(targets, VLA_CENTER, _gaussian_line(2.0, 50.0)))
    tab = Table({"ra": [ra0, ra0 + 0.02], "dec": [dec0, dec0], "z": HI / np.array([nu_a, nu_b]) - 1})
    kw = dict(line_frequency=HI, velocity_resolution=30.0, velocity_range=(-300, 300),
              primary_beam="none", weighting="none")
    both = stack_lines(ds, tab, **kw)
    alone = stack_lines(ds, tab[:1], **kw)
    assert set(both.n_targets_per_bin) == {1, 2}
    only_a = both.n_targets_per_bin == 1
    # B's band edge is below its line centre: it covers the high-frequency, negative v side
    assert only_a[-1] and not only_a[0]
    np.testing.assert_allclose(both.flux_jy[only_a], alone.flux_jy[only_a], rtol=1e-12)
    assert not np.allclose(both.flux_jy[~only_a], alone.flux_jy[~only_a])
    assert both.positions["n_bins"].tolist() == [20, int((~only_a).sum())]


def test_line_outside_band_warns():
    """A target whose line misses the band is not stacked, with a warning naming the option."""
    from xstack.errors import XstackWarning

    ra0, dec0 = np.degrees(VLA_CENTER)
    ds = _partition(seed=6, frame="LSRK")
    tab = Table({"ra": [ra0, ra0], "dec": [dec0, dec0],
                 "z": HI / np.array([1.3024e9, 1.1e9]) - 1})
    with pytest.warns(XstackWarning, match="1 of 2 targets.*velocity_range"):
        res = stack_lines(ds, tab, line_frequency=HI, primary_beam="none")
    assert res.n_positions == 1
    assert res.positions["n_bins"][1] == 0


# --- regridding -----------------------------------------------------------------------------

def test_overlap_lengths_conserve_integral():
    rng = np.random.default_rng(0)
    src = np.sort(rng.uniform(-500, 500, size=80))
    dst = np.sort(rng.uniform(-600, 600, size=31))
    o = overlap_lengths(src, dst)
    inside = np.clip(np.minimum(src[1:], dst[-1]) - np.maximum(src[:-1], dst[0]), 0, None)
    np.testing.assert_allclose(o.sum(axis=1), inside, rtol=0, atol=1e-9)
    # densities regridded: the integral over the grid is conserved
    f = rng.normal(size=src.size - 1)
    assert np.sum(f @ o) == pytest.approx(np.sum(f * inside), rel=1e-6, abs=1e-9)
    # decreasing edges and (n, 2) intervals give the same
    np.testing.assert_allclose(overlap_lengths(src[::-1], dst)[::-1], o, atol=1e-12)
    np.testing.assert_allclose(overlap_lengths(np.column_stack([src[1:], src[:-1]]), dst), o,
                               atol=1e-12)
    # the stacked spectrum of a flat-spectrum source integrates to flux x the range
    edges = velocity_edges(20, (-600, 600))
    assert edges.size == 61 and edges[-1] == 600
    assert velocity_edges(7, (-10, 10))[-1] >= 10


def test_line_centres_from_z_and_freq():
    import astropy.units as u

    from xstack.errors import XstackError

    t = Table({"z": [0.0, 0.1]})
    np.testing.assert_allclose(line_centres_hz(t, HI), [HI, HI / 1.1])
    t = Table({"freq": [1.3, 1.4] * u.GHz})
    np.testing.assert_allclose(line_centres_hz(t, HI), [1.3e9, 1.4e9])
    with pytest.raises(XstackError, match="rows 2"):
        line_centres_hz(Table({"z": [0.1, -1.5]}), HI)
    with pytest.raises(XstackError, match="column z"):
        line_centres_hz(Table({"ra": [1.0]}), HI)


# --- Doppler tracking ------------------------------------------------------------------------

def test_topo_track_stacks_as_sharply_as_lsrk(monkeypatch):
    """TOPO data whose frequencies move by a known ratio per integration stack as sharply as
    LSRK data; without the correction the line is visibly broader."""
    import xstack.frames

    n_time = 12
    # a strong made-up track: +-100 km/s over the observation
    track = 1 + (100 / SPEED_OF_LIGHT_KMS) * np.linspace(-1, 1, n_time)
    ra0, dec0 = np.degrees(VLA_CENTER)
    nus = 1.30e9 + 50e3 * np.array([22, 74])
    targets = [(VLA_CENTER[0], VLA_CENTER[1], nus[0]),
               (VLA_CENTER[0] + np.radians(0.02), VLA_CENTER[1] - np.radians(0.01), nus[1])]
    tab = Table({"ra": [ra0, ra0 + 0.02], "dec": [dec0, dec0 - 0.01], "z": HI / nus - 1})
    profile = _gaussian_line(3.0, 30.0)
    kw = dict(n_time=n_time, seed=7, sigma=0.05, dfreq=50e3, n_chan=96)
    lsrk = _partition(frame="LSRK", vis=_line_vis(targets, VLA_CENTER, profile), **kw)
    topo = _partition(vis=_line_vis(targets, VLA_CENTER, profile, ratio=track), **kw)
    times = topo["time"].values

    def known_track(time_s, ra_deg, dec_deg, location, *, to_frame, from_frame="TOPO"):
        assert from_frame == "TOPO" and to_frame == "LSRK"
        return np.interp(np.asarray(time_s), times, track)

    stack = dict(line_frequency=HI, velocity_resolution=10.0, velocity_range=(-250, 250),
                 primary_beam="none", weighting="none")
    monkeypatch.setattr(xstack.frames, "frame_ratio", known_track)
    p_l, e_l = _fit_gaussian(stack_lines(lsrk, tab, **stack))
    p_t, e_t = _fit_gaussian(stack_lines(topo, tab, **stack))
    monkeypatch.setattr(xstack.frames, "frame_ratio",
                        lambda t, *a, **k: np.ones(np.shape(t)))
    p_u, e_u = _fit_gaussian(stack_lines(topo, tab, **stack))
    assert abs(p_t[2] - p_l[2]) < 3 * np.hypot(e_t[2], e_l[2])
    assert abs(p_t[2] - 30.0) < 4 * e_t[2]
    # a Gaussian of 30 km/s smeared over the +-100 km/s track: ~65 km/s
    assert p_u[2] > 1.5 * p_l[2]
    assert p_u[2] > p_l[2] + 5 * np.hypot(e_u[2], e_l[2])


def test_data_in_another_frame_is_an_error():
    from xstack.errors import OptionError

    ra0, dec0 = np.degrees(VLA_CENTER)
    ds = _partition(seed=8, frame="BARY")
    tab = Table({"ra": [ra0], "dec": [dec0], "z": [HI / 1.3024e9 - 1]})
    with pytest.raises(OptionError, match="frame BARY") as info:
        stack_lines(ds, tab, line_frequency=HI, frame="lsrk", primary_beam="none")
    assert info.value.option == "frame"
    # in its own frame the same data stack
    assert stack_lines(ds, tab, line_frequency=HI, frame="bary", primary_beam="none").n_positions == 1


# --- hard cases, as in the continuum stack -------------------------------------------------

@pytest.mark.parametrize("where", ["pole", "ra_wrap", "damaged"])
def test_flat_spectrum_equals_continuum_stack(where):
    """A flat-spectrum source: every covered bin holds the continuum stack's flux (noiseless
    to 1e-6) — at the pole, across RA = 0, and with flagged rows/channels, zero weights and
    NaN data (which enter neither stack)."""
    from xstack.uvstack.stack import stack_uv

    center = {"pole": (np.radians(10.0), np.radians(89.95)),
              "ra_wrap": (np.radians(0.01), np.radians(20.0)),
              "damaged": VLA_CENTER}[where]
    # one target (a second one's sidelobes would be real signal in both stacks): across the
    # pole, across RA = 0 from the phase centre, or beside it
    ra_t, dec_t = {"pole": (np.radians([190.0]), np.radians([89.99])),
                   "ra_wrap": (np.radians([359.96]), np.radians([20.01])),
                   "damaged": (center[0] + np.radians([0.02]), center[1] + np.radians([-0.01]))
                   }[where]
    def flat(uvw, freq):
        out = np.zeros(uvw.shape[:2] + (freq.size,), dtype=np.complex128)
        for ra, dec in zip(ra_t, dec_t):
            l, m, _n, n1 = radec_to_lmn(np.array([ra]), np.array([dec]), *center)
            d = uvw @ np.array([l[0], m[0], n1[0]])
            out += 0.5 * np.exp(2j * np.pi * d[..., None] * freq / SPEED_OF_LIGHT)
        return out

    ds = _partition(seed=9, center=center, frame="LSRK", vis=flat, sigma=0.0)
    if where == "damaged":
        ds = _damage(ds, 3)
    tab = Table({"ra": np.degrees(ra_t), "dec": np.degrees(dec_t),
                 "z": HI / (1.30e9 + 100e3 * np.array([20])) - 1})
    if where == "ra_wrap":
        assert tab["ra"][0] > 359 and np.degrees(center[0]) < 1
    res = stack_lines(ds, tab, line_frequency=HI, primary_beam="none", weighting="none",
                      velocity_resolution=40, velocity_range=(-400, 400))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # noiseless: its measured error is zero
        cont = stack_uv(ds, tab, primary_beam="none", weighting="none", smearing="none")
    ok = np.isfinite(res.flux_jy)
    assert ok.sum() >= 15
    np.testing.assert_allclose(res.flux_jy[ok], 0.5, rtol=0, atol=1e-6)
    assert cont.flux_jy == pytest.approx(0.5, abs=1e-6)
    # the same visibilities are usable in both (NaN and zero weights in neither)
    assert res.n_visibilities <= cont.n_visibilities


def test_writes_stacked_store(tmp_path):
    """out=: a stacked store on the velocity axis whose weighted mean per bin over rows is
    the line spectrum."""
    from xstack.schema import iter_partitions, open_store, validate_store

    ra0, dec0 = np.degrees(VLA_CENTER)
    nu = 1.30e9 + 100e3 * 24
    ds = _partition(seed=10, frame="LSRK", sigma=0.0,
                    vis=_line_vis([(VLA_CENTER[0], VLA_CENTER[1], nu)], VLA_CENTER,
                                  _gaussian_line(2.0, 50.0)))
    tab = Table({"ra": [ra0], "dec": [dec0], "z": [HI / nu - 1]})
    kw = dict(line_frequency=HI, velocity_resolution=30.0, velocity_range=(-300, 300),
              primary_beam="none", weighting="none")
    res = stack_lines(ds, tab, out=tmp_path / "s.zarr", **kw)
    assert res.out == str(tmp_path / "s.zarr")
    attrs = validate_store(tmp_path / "s.zarr")
    assert attrs["xstack_kind"] == "stacked"
    np.testing.assert_array_equal(np.array(attrs["linestack"]["flux_jy"], dtype=float),
                                  res.flux_jy)
    (_, p), = iter_partitions(open_store(tmp_path / "s.zarr"))
    assert p.attrs["spectral_axis"] == "velocity"
    np.testing.assert_allclose(p["velocity"].values, res.velocity_kms)
    vis = p["VISIBILITY"].values
    w = p["WEIGHT"].values
    good = ~p["FLAG"].values
    mean = np.nansum(np.where(good, vis.real * w, 0), axis=(0, 1, 3)) / np.sum(
        np.where(good, w, 0), axis=(0, 1, 3))
    # (the rows weigh channels by their own weights: close, not equal, to the flux)
    np.testing.assert_allclose(mean, res.flux_jy, rtol=0, atol=0.02 * np.nanmax(res.flux_jy))
    # the flux of the written run is the flux of a run without out
    np.testing.assert_array_equal(stack_lines(ds, tab, **kw).flux_jy, res.flux_jy)


# --- lazy and distributed -------------------------------------------------------------------

@pytest.fixture(scope="module")
def cluster():
    from _cluster_helpers import local_cluster

    with local_cluster() as c:
        yield c


def test_distributed_equals_threaded_bitwise(cluster):
    """Several time chunks: the line stack on a 2-process LocalCluster (its tasks run there)
    gives the threaded run's spectrum and covariance to the last bit."""
    import distributed

    ra0, dec0 = np.degrees(VLA_CENTER)
    ds = _damage(_partition(seed=12, n_time=12, frame="LSRK"), 4).chunk({"time": 3})
    tab = Table({"ra": [ra0, ra0 + 0.02], "dec": [dec0, dec0 + 0.01],
                 "z": HI / (1.30e9 + 100e3 * np.array([20, 28])) - 1})
    kw = dict(line_frequency=HI, velocity_resolution=25.0, velocity_range=(-200, 200),
              primary_beam="none")
    threaded = stack_lines(ds, tab, **kw)
    before = cluster.counter.finished
    with distributed.Client(cluster) as client:
        assert client.run(lambda: 1)
        on_cluster = stack_lines(ds, tab, **kw)
    assert cluster.counter.finished - before >= 4  # the chunks' tasks ran on the workers
    assert on_cluster.flux_jy.tobytes() == threaded.flux_jy.tobytes()
    assert on_cluster.flux_cov_jy2.tobytes() == threaded.flux_cov_jy2.tobytes()
    np.testing.assert_array_equal(on_cluster.n_targets_per_bin, threaded.n_targets_per_bin)


def test_options_checked_and_no_data():
    """Bad options name the parameter before any data are read; a catalog whose lines all
    miss the band is NoDataError; a freq column (with units) is used as the line centre."""
    import astropy.units as u

    from xstack.errors import NoDataError, OptionError

    ra0, dec0 = np.degrees(VLA_CENTER)
    tab = Table({"ra": [ra0], "dec": [dec0], "z": [0.0]})
    for kw, option in ((dict(frame="topo"), "frame"), (dict(velocity_resolution=0), "velocity_resolution"),
                       (dict(velocity_range=(10, -10)), "velocity_range"),
                       (dict(line_frequency="XY(9-8)"), "line_frequency")):
        args = {"line_frequency": HI, **kw}
        with pytest.raises(OptionError) as info:
            stack_lines("/nonexistent.zarr", tab, **args)
        assert info.value.option == option
    ds = _partition(seed=13, frame="LSRK", sigma=0.0,
                    vis=_line_vis([(VLA_CENTER[0], VLA_CENTER[1], 1.3024e9)], VLA_CENTER,
                                  _gaussian_line(1.0, 40.0)))
    with pytest.raises(NoDataError), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        stack_lines(ds, tab, line_frequency=HI, primary_beam="none")  # z = 0: 1.42 GHz
    by_z = stack_lines(ds, Table({"ra": [ra0], "dec": [dec0], "z": [HI / 1.3024e9 - 1]}),
                       line_frequency=HI, primary_beam="none")
    by_freq = stack_lines(ds, Table({"ra": [ra0], "dec": [dec0], "freq": [1302.4] * u.MHz}),
                          line_frequency=HI, primary_beam="none")
    np.testing.assert_allclose(by_freq.flux_jy, by_z.flux_jy, rtol=1e-9, atol=1e-12)
    assert np.nansum(by_z.flux_jy) * 20 == pytest.approx(1.0, rel=1e-3)


def _lazy_store(tmp_path):
    """A store of several time chunks with two targets' lines, and its catalog."""
    from xstack.schema import write_store

    ra0, dec0 = np.degrees(VLA_CENTER)
    nus = 1.30e9 + 100e3 * np.array([20, 28])
    targets = [(VLA_CENTER[0], VLA_CENTER[1], nus[0]),
               (VLA_CENTER[0] + np.radians(0.02), VLA_CENTER[1] + np.radians(0.01), nus[1])]
    ds = _partition(seed=14, n_time=12, frame="LSRK",
                    vis=_line_vis(targets, VLA_CENTER, _gaussian_line(2.0, 40.0)))
    path = tmp_path / "data.zarr"
    write_store({"p": _damage(ds, 5).chunk({"time": 3})}, path)
    tab = Table({"ra": [ra0, ra0 + 0.02], "dec": [dec0, dec0 + 0.01], "z": HI / nus - 1})
    return path, tab


def test_lazy_equals_eager_and_reads_each_chunk_once(tmp_path):
    """compute=False: a LazyResult computing to the eager result to the last bit (with .compute,
    xstack.compute and dask.compute); computed beside a lazy continuum stack of the same data,
    each VISIBILITY chunk is read once."""
    import dask
    from _uvstack_helpers import CountVisibilityReads

    import xstack
    from xstack._lazy import LazyResult
    from xstack.schema import open_store

    path, tab = _lazy_store(tmp_path)
    tree = open_store(path)
    kw = dict(line_frequency=HI, velocity_resolution=25.0, velocity_range=(-200, 200),
              primary_beam="none")
    eager = stack_lines(tree, tab, **kw)
    lazy = stack_lines(tree, tab, compute=False, **kw)
    assert isinstance(lazy, LazyResult) and dask.is_dask_collection(lazy)
    for res in (lazy.compute(), xstack.compute(lazy)[0], dask.compute(lazy)[0]):
        assert isinstance(res, type(eager))
        assert res.flux_jy.tobytes() == eager.flux_jy.tobytes()
        assert res.flux_cov_jy2.tobytes() == eager.flux_cov_jy2.tobytes()
        np.testing.assert_array_equal(res.n_targets_per_bin, eager.n_targets_per_bin)
        assert (res.n_visibilities, res.n_positions) == (eager.n_visibilities, eager.n_positions)
    cont = xstack.stack_uv(tree, tab, primary_beam="none")
    with dask.config.set(scheduler="sync"):
        with CountVisibilityReads() as one:
            stack_lines(tree, tab, compute=False, **kw).compute()
        with CountVisibilityReads() as both:
            rc, rl = xstack.compute(xstack.stack_uv(tree, tab, primary_beam="none", compute=False),
                                    stack_lines(tree, tab, compute=False, **kw))
    assert one.reads == len(tree["p"]["VISIBILITY"].chunks[0]) == 4
    assert both.reads == one.reads  # the continuum and the line stack: one read per chunk
    assert rl.flux_jy.tobytes() == eager.flux_jy.tobytes()
    assert rc.flux_jy == cont.flux_jy


def test_lazy_with_out_writes_the_eager_store(tmp_path, monkeypatch):
    """compute=False with out: nothing is a store before the compute; after it the store
    equals the eager run's (arrays and spectrum); a failed compute leaves nothing."""
    import xstack
    import xstack.uvstack.line as line_module
    from xstack.schema import open_store

    path, tab = _lazy_store(tmp_path)
    kw = dict(line_frequency=HI, velocity_resolution=25.0, velocity_range=(-200, 200),
              primary_beam="none")
    eager = stack_lines(path, tab, out=tmp_path / "e.zarr", **kw)
    lazy = stack_lines(path, tab, out=tmp_path / "l.zarr", compute=False, **kw)
    assert not (tmp_path / "l.zarr").exists()
    (res,) = xstack.compute(lazy)
    assert res.out == str(tmp_path / "l.zarr")
    assert res.flux_jy.tobytes() == eager.flux_jy.tobytes()
    a, b = open_store(tmp_path / "e.zarr"), open_store(tmp_path / "l.zarr")
    assert a.attrs["linestack"] == b.attrs["linestack"]
    for name in ("VISIBILITY", "WEIGHT", "FLAG"):
        np.testing.assert_array_equal(a["p"][name].values, b["p"][name].values)

    real = line_module._block_line
    calls = []

    def failing(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise RuntimeError("injected chunk failure")
        return real(*args, **kwargs)

    monkeypatch.setattr(line_module, "_block_line", failing)
    lazy = stack_lines(path, tab, out=tmp_path / "f.zarr", compute=False, **kw)
    with pytest.raises(RuntimeError, match="injected"):
        xstack.compute(lazy)
    assert calls
    assert not (tmp_path / "f.zarr").exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".f.zarr")] == []
