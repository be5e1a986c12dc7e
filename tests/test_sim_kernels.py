"""Equation-1 kernel against analytic answers and an independent numpy evaluation."""

from __future__ import annotations

import numpy as np
import pytest
from _sim_helpers import direct_eq1

from xstack.coords import radec_to_lmn
from xstack.sim import kernels
from xstack.sim.kernels import model_visibilities


def _uvw(rng, n=200, scale=3000.0):
    return rng.normal(scale=scale, size=(n, 3))


def test_point_source_at_phase_center_is_constant(rng):
    uvw = _uvw(rng)
    freq = np.linspace(1.3e9, 1.5e9, 7)
    with kernels.record_steps() as steps:
        vis = model_visibilities(uvw, freq, [0.0], [0.0], [0.0], [0.01])
    assert np.all(vis == 0.01 + 0j)
    assert steps == {"constant": 1}  # no phasors, no w-term, no Gaussian


@pytest.mark.parametrize("uniform", [True, False])
def test_offset_sources_match_direct_eq1(rng, uniform):
    ra0, dec0 = np.radians(57.29), np.radians(-30.0)
    ra = ra0 + rng.uniform(-0.01, 0.01, 40)
    dec = dec0 + rng.uniform(-0.01, 0.01, 40)
    l, m, _, nm1 = radec_to_lmn(ra, dec, ra0, dec0)
    flux = rng.uniform(1e-6, 1e-2, 40)
    uvw = _uvw(rng, 300, 10000.0)
    freq = (np.linspace(1.275e9, 1.525e9, 70) if uniform
            else np.sort(rng.uniform(1.275e9, 1.525e9, 70)))
    att = rng.uniform(0.2, 1.0, (40, 70))
    ref = direct_eq1(uvw, freq, l, m, nm1, flux, att)
    for parallel in (True, False):
        got = model_visibilities(uvw, freq, l, m, nm1, flux, att, parallel=parallel)
        err = np.abs(got - ref).max() / np.abs(flux).sum()
        assert err < 1e-9, err


def test_descending_channels_and_single_channel(rng):
    l, m = np.array([1e-3, -2e-3]), np.array([5e-4, 1e-3])
    nm1 = -(l**2 + m**2) / (1 + np.sqrt(1 - l**2 - m**2))
    uvw = _uvw(rng, 50)
    freq = np.linspace(2.32e11, 2.28e11, 100)
    ref = direct_eq1(uvw, freq, l, m, nm1, [1.0, 2.0])
    got = model_visibilities(uvw, freq, l, m, nm1, [1.0, 2.0])
    assert np.abs(got - ref).max() < 1e-9 * 3
    got1 = model_visibilities(uvw, freq[:1], l, m, nm1, [1.0, 2.0])
    assert np.abs(got1 - ref[:, :1]).max() < 1e-9 * 3


def test_w_term_skipped_when_not_asked(rng):
    uvw = _uvw(rng)
    freq = np.array([1.4e9])
    l, m = np.array([0.01]), np.array([0.02])
    with kernels.record_steps() as steps:
        a = model_visibilities(uvw, freq, l, m, None, [1.0])
    assert "w_term" not in steps and steps["phase"] == 1
    # without a w-term the w column has no influence at all
    uvw2 = uvw.copy()
    uvw2[:, 2] = 0.0
    assert np.array_equal(a, model_visibilities(uvw2, freq, l, m, None, [1.0]))
    with kernels.record_steps() as steps:
        model_visibilities(uvw, freq, l, m, [-2.5e-4], [1.0])
    assert steps["w_term"] == 1


def test_gaussian_matches_analytic_transform(rng):
    """A circular Gaussian of FWHM theta has V = S exp(-pi^2 theta^2 q^2 / (4 ln2 lambda^2))."""
    theta = np.radians(3.0 / 3600)
    uvw = np.zeros((60, 3))
    uvw[:, 0] = np.linspace(0, 40000, 60)
    uvw[:, 1] = np.linspace(0, -10000, 60)
    freq = np.linspace(1.3e9, 1.5e9, 11)
    with kernels.record_steps() as steps:
        vis = model_visibilities(uvw, freq, [0.0], [0.0], [0.0], [2.0], fwhm=[theta])
    assert steps["gaussian"] == 1
    q = np.hypot(uvw[:, 0], uvw[:, 1])[:, None]
    lam = 299792458.0 / freq[None, :]
    expect = 2.0 * np.exp(-np.pi**2 * theta**2 * q**2 / (4 * np.log(2) * lam**2))
    assert np.allclose(vis.imag, 0.0, atol=1e-15)
    # absolute agreement to 1e-12 of the flux; the tiny far tail (< 1e-30) is dropped
    assert np.abs(vis.real - expect).max() < 2e-12
    # half the peak amplitude where q/lambda = 2 ln 2 / (pi theta): the FWHM definition
    qh = 2 * np.log(2) / (np.pi * theta) * lam[0, 0]
    half = model_visibilities(np.array([[qh, 0.0, 0.0]]), freq[:1], [0.0], [0.0], None, [1.0],
                              fwhm=[theta])
    assert half[0, 0].real == pytest.approx(0.5, rel=1e-12)


def test_extended_offset_sources_match_direct(rng):
    l = rng.uniform(-5e-3, 5e-3, 30)
    m = rng.uniform(-5e-3, 5e-3, 30)
    nm1 = -(l**2 + m**2) / (1 + np.sqrt(1 - l**2 - m**2))
    fwhm = np.where(rng.uniform(size=30) < 0.5, 0.0, np.radians(rng.uniform(0.5, 5, 30) / 3600))
    uvw = _uvw(rng, 200, 5000.0)
    freq = np.linspace(1.275e9, 1.525e9, 10)
    flux = rng.uniform(0, 1, 30)
    ref = direct_eq1(uvw, freq, l, m, nm1, flux, fwhm=fwhm)
    got = model_visibilities(uvw, freq, l, m, nm1, flux, fwhm=fwhm)
    assert np.abs(got - ref).max() / flux.sum() < 1e-9


def test_recurrence_error_bounded_for_many_channels(rng):
    """4000 channels at 36 km baselines: the channel recurrence stays at ~1e-12."""
    uvw = rng.normal(scale=20000.0, size=(20, 3))
    freq = 1.0e9 + 1e5 * np.arange(4000)
    l, m = np.array([0.02]), np.array([-0.015])
    nm1 = -(l**2 + m**2) / (1 + np.sqrt(1 - l**2 - m**2))
    ref = direct_eq1(uvw, freq, l, m, nm1, [1.0])
    got = model_visibilities(uvw, freq, l, m, nm1, [1.0])
    assert np.abs(got - ref).max() < 1e-10


def test_complex64_output_and_empty(rng):
    uvw = _uvw(rng, 10)
    out = model_visibilities(uvw, [1e9], [1e-3], [0.0], None, [1.0], out_dtype=np.complex64)
    assert out.dtype == np.complex64
    empty = model_visibilities(uvw, [1e9], [], [], None, [])
    assert empty.shape == (10, 1) and not empty.any()


@pytest.mark.parametrize("uniform", [True, False])
def test_antenna_kernel_equals_baseline_kernel(rng, uniform):
    """Per-antenna phasors give the baseline sum (points and Gaussians, w-term, beam)."""
    from xstack.schema import baseline_pairs
    from xstack.sim.kernels import model_visibilities_antenna

    nant, nt, nsrc = 9, 4, 25
    ant = rng.normal(scale=8000.0, size=(nt, nant, 3))
    a1, a2 = baseline_pairs(nant)
    uvw = (ant[:, a1] - ant[:, a2]).reshape(-1, 3)
    freq = (np.linspace(1.3e9, 1.5e9, 12) if uniform
            else np.sort(rng.uniform(1.3e9, 1.5e9, 12))[::-1].copy())
    l = rng.uniform(-5e-3, 5e-3, nsrc)
    m = rng.uniform(-5e-3, 5e-3, nsrc)
    l[0] = m[0] = 0.0  # one at the phase center
    nm1 = -(l**2 + m**2) / (1 + np.sqrt(1 - l**2 - m**2))
    flux = rng.uniform(0, 1, nsrc)
    att = rng.uniform(0.1, 1, (nsrc, 12))
    fwhm = np.where(rng.uniform(size=nsrc) < 0.4, np.radians(rng.uniform(0.5, 5, nsrc) / 3600), 0)
    ref = direct_eq1(uvw, freq, l, m, nm1, flux, att, fwhm).reshape(nt, a1.size, 12)
    got = model_visibilities_antenna(ant, a1, a2, freq, l, m, nm1, flux, att, fwhm)
    assert np.abs(got - ref).max() / flux.sum() < 1e-9
    ser = model_visibilities_antenna(ant, a1, a2, freq, l, m, nm1, flux, att, fwhm,
                                     parallel=False)
    assert np.array_equal(ser, got)
    with kernels.record_steps() as steps:
        model_visibilities_antenna(ant, a1, a2, freq, [0.0], [0.0], None, [1.0])
    assert steps == {"constant": 1}
