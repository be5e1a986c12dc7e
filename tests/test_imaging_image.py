"""make_image on partitions and stores: flux, position, WCS, weighting, streaming, errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
from _imaging_helpers import PHASE_CENTER, make_sky_partition, offset_position
from astropy import units as u
from astropy.coordinates import SkyCoord

from xstack.errors import XstackError
from xstack.imaging.fitsio import read_image
from xstack.imaging.image import make_image, predict
from xstack.imaging.kernels import direct_dirty_image
from xstack.schema import write_store

ARCSEC = math.pi / 180 / 3600


@pytest.fixture(scope="module")
def point_partition():
    # 1.5 Jy source 24" east and 12" south of the phase center; cells of 2" put it on a pixel
    src = offset_position(24.0, -12.0)
    return make_sky_partition([(src[0], src[1], 1.5)], n_time=16, n_ant=10), src


def test_dirty_image_peak_position_and_flux(point_partition):
    ds, src = point_partition
    res = make_image(ds, size=128, cell_arcsec=2.0)
    img = res.image
    y, x = np.unravel_index(np.argmax(img), img.shape)
    # east is to the left: x decreases by 12 pixels; south: y decreases by 6
    assert (y - 64, x - 64) == pytest.approx((-6, -12), abs=0)
    # the source sits within 0.03 pixel of the pixel center (SIN vs offsets): ~no pixel loss
    assert img[y, x] == pytest.approx(1.5, rel=1e-3)
    assert res.psf[64, 64] == pytest.approx(1.0, abs=1e-6)
    assert res.psf.max() == pytest.approx(1.0, abs=1e-6)
    # WCS: the brightest pixel's world position is the source (within 0.1 pixel)
    ra, dec = res.wcs.pixel_to_world_values(x, y)
    sep = SkyCoord(ra * u.deg, dec * u.deg).separation(SkyCoord(src[0] * u.rad, src[1] * u.rad))
    assert sep.arcsec < 0.2
    # and the phase center is at the reference pixel
    ra0, dec0 = res.wcs.pixel_to_world_values(64, 64)
    assert ra0 == pytest.approx(math.degrees(PHASE_CENTER[0]), abs=1e-9)
    assert dec0 == pytest.approx(math.degrees(PHASE_CENTER[1]), abs=1e-9)
    bmaj, bmin, _ = res.beam
    assert bmaj >= bmin > 2.0  # several pixels: a sampled beam


def test_dirty_image_matches_direct_fourier_sum():
    ds = make_sky_partition([(*offset_position(200.0, 150.0), 1.0)], n_time=4, n_ant=6,
                            n_chan=3, noise=0.3, flag_fraction=0.1, max_baseline=800.0)
    res = make_image(ds, size=48, cell_arcsec=20.0, epsilon=1e-9)
    vis = ds.VISIBILITY.values
    w = ds.WEIGHT.values * ~ds.FLAG.values
    uvw = ds.UVW.values.reshape(-1, 3)
    freq = ds.frequency.values
    ref = sum(direct_dirty_image(uvw, freq, vis[..., p].reshape(-1, 3), w[..., p].reshape(-1, 3),
                                 48, 48, 20 * ARCSEC) for p in range(2)) / w.sum()
    assert np.max(np.abs(res.image - ref)) < 1e-5 * np.max(np.abs(ref))
    assert res.sum_weights == pytest.approx(w.sum(), rel=1e-6)


def test_streamed_store_equals_in_memory(tmp_path, point_partition):
    ds, _ = point_partition
    path = tmp_path / "s.zarr"
    write_store({"spw0_field0": ds.chunk({"time": 3, "baseline_id": 20})}, path)
    a = make_image(ds, size=64, cell_arcsec=2.0, weighting="briggs", robust=0.5)
    b = make_image(path, size=64, cell_arcsec=2.0, weighting="briggs", robust=0.5)
    assert np.allclose(a.image, b.image, atol=1e-7)
    assert np.allclose(a.psf, b.psf, atol=1e-7)
    # one ducc0 call per store chunk (no batching) gives the same image
    from xstack.imaging.image import Imager

    imager = Imager(path, size=64, cell_arcsec=2.0, weighting="briggs", robust=0.5)
    imager.batch_visibilities = 1
    c = imager.dirty_and_psf()
    assert np.allclose(c["dirty"], b.image, atol=1e-7)
    assert c["sum_weights"] == pytest.approx(b.sum_weights, rel=1e-12)


def test_weightings_change_beam_not_flux(point_partition):
    ds, _ = point_partition
    beams = {}
    for wt in ("natural", "briggs", "uniform"):
        r = make_image(ds, size=128, cell_arcsec=2.0, weighting=wt)
        assert r.psf[64, 64] == pytest.approx(1.0, abs=1e-6)
        assert r.image.max() == pytest.approx(1.5, rel=2e-3)
        beams[wt] = r.beam[0] * r.beam[1]
    assert beams["uniform"] < beams["briggs"] < beams["natural"]


def test_stokes_i_uses_each_hand_with_its_weight():
    """XX carries 2 Jy, YY 0 Jy with 3x the weight: weighted mean of the hands = 0.5 Jy."""
    ds = make_sky_partition([(*PHASE_CENTER, 1.0)], n_time=4, n_ant=6)
    vis = ds.VISIBILITY.values.copy()
    vis[..., 0] *= 2.0
    vis[..., 1] = 0.0
    w = ds.WEIGHT.values.copy()
    w[..., 1] *= 3.0
    ds = ds.assign(VISIBILITY=(ds.VISIBILITY.dims, vis), WEIGHT=(ds.WEIGHT.dims, w))
    r = make_image(ds, size=32, cell_arcsec=5.0)
    assert r.image[16, 16] == pytest.approx(0.5, rel=1e-5)


def test_pbcor_divides_by_beam():
    src = offset_position(600.0, 0.0)  # 10' east: VLA L-band beam attenuation ~0.7
    ds = make_sky_partition([(src[0], src[1], 1.0)], n_time=8, n_ant=10, telescope="VLA")
    a = make_image(ds, size=256, cell_arcsec=5.0)
    b = make_image(ds, size=256, cell_arcsec=5.0, pbcor=True)
    y, x = np.unravel_index(np.argmax(a.image), a.image.shape)
    assert b.primary_beam is not None and 0.3 < b.primary_beam[y, x] < 0.99
    assert b.image[y, x] == pytest.approx(a.image[y, x] / b.primary_beam[y, x], rel=1e-9)
    assert b.header["XSPBCOR"] is True


def test_fits_roundtrip_world_position(tmp_path, point_partition):
    ds, src = point_partition
    res = make_image(ds, size=128, cell_arcsec=2.0)
    path = res.write(tmp_path / "img.fits")
    data, wcs, header = read_image(path)
    assert header["NAXIS"] == 4 and header["CTYPE1"] == "RA---SIN" and header["CTYPE2"] == "DEC--SIN"
    assert header["BUNIT"] == "Jy/beam"
    assert header["BMAJ"] * 3600 == pytest.approx(res.beam[0])
    y, x = np.unravel_index(np.argmax(data), data.shape)
    world = wcs.pixel_to_world(x, y)
    assert world.separation(SkyCoord(src[0] * u.rad, src[1] * u.rad)).arcsec < 0.2
    # astropy's own full 4-D WCS agrees
    from astropy.io import fits
    from astropy.wcs import WCS

    full = WCS(fits.getheader(path))
    assert full.naxis == 4 and full.celestial.wcs.ctype[0] == "RA---SIN"


def test_adjoint_on_store_geometry(rng, point_partition):
    ds, _ = point_partition
    uvw = ds.UVW.values
    freq = ds.frequency.values
    x = rng.normal(size=(64, 64))
    y = rng.normal(size=uvw.shape[:2] + (freq.size,)) + 1j * rng.normal(size=uvw.shape[:2] + (freq.size,))
    from xstack.imaging.image import grid_visibilities

    lhs = np.sum(grid_visibilities(uvw.reshape(-1, 3), freq, y.reshape(-1, freq.size),
                                   np.ones((y.size // freq.size, freq.size)), 64, 64, 3 * ARCSEC,
                                   epsilon=1e-10) * x)
    rhs = np.real(np.vdot(predict(x, 3.0, uvw, freq, epsilon=1e-10), y))
    assert abs(lhs - rhs) < 1e-6 * abs(lhs)


def test_mosaic_selection_and_bad_input_errors(tmp_path):
    from xstack.imaging.clean import clean_data
    from xstack.imaging.image import Imager

    a = make_sky_partition(n_time=2, n_ant=4, field_id=0)
    b = make_sky_partition(n_time=2, n_ant=4, field_id=1,
                           phase_center=(PHASE_CENTER[0] + 1e-4, PHASE_CENTER[1]))
    path = tmp_path / "m.zarr"
    write_store({"spw0_field0": a, "spw0_field1": b}, path)
    # CLEAN needs one pointing; the dirty imager makes a linear mosaic instead
    with pytest.raises(XstackError, match="different phase centers"):
        clean_data(path, size=32, cell_arcsec=1.0, niter=5)
    with pytest.raises(XstackError, match="different phase centers"):
        Imager(path, size=32, cell_arcsec=1.0)
    assert make_image(path, size=32, cell_arcsec=1.0).header["XSMOSAIC"] == 2
    r = make_image(path, size=32, cell_arcsec=1.0, partitions="*field1")
    assert r.partitions == ("spw0_field1",) and "XSMOSAIC" not in r.header
    assert r.wcs.wcs.crval[0] == pytest.approx(math.degrees(PHASE_CENTER[0] + 1e-4))
    with pytest.raises(XstackError, match="no partition matches"):
        make_image(path, size=32, cell_arcsec=1.0, partitions="nope")
    with pytest.raises(XstackError, match="even"):
        make_image(a, size=33, cell_arcsec=1.0)
    with pytest.raises(XstackError, match="weighting"):
        make_image(a, size=32, cell_arcsec=1.0, weighting="robust")
    cross = make_sky_partition(n_time=2, n_ant=4, pols=("XY", "YX"))
    with pytest.raises(XstackError, match="parallel-hand"):
        make_image(cross, size=32, cell_arcsec=1.0)
    flagged = a.assign(FLAG=(a.FLAG.dims, np.ones(a.FLAG.shape, bool)))
    with pytest.raises(XstackError, match="no unflagged"):
        make_image(flagged, size=32, cell_arcsec=1.0)


def _alma_mosaic(src_flux, src, offsets, noise=0.0, n_time=6, n_ant=10, seed=0):
    """ALMA pointings at ``offsets`` (arcsec east, north) seeing ``src`` through their beam."""
    from xstack.beams import standard_beam
    from xstack.coords import angular_separation

    beam = standard_beam("ALMA", 12.0)
    freq = 230e9 + 100e6 * np.arange(3)
    parts = {}
    for field, (dx, dy) in enumerate(offsets):
        center = offset_position(dx, dy)
        att = beam(angular_separation(*center, *src), freq)[None, :]
        parts[f"spw0_field{field}"] = make_sky_partition(
            [(src[0], src[1], src_flux)], n_time=n_time, n_ant=n_ant, freq0=230e9,
            chan_width=100e6, n_chan=3, telescope="ALMA", dish=12.0, max_baseline=400.0,
            phase_center=center, field_id=field, attenuation=att, noise=noise, seed=seed + field)
    return parts, beam, freq


def test_linear_mosaic_equals_direct_fourier_sum(tmp_path):
    """Each pointing's direct Fourier sum at every mosaic pixel's sky direction, combined as
    sum A_p D_p / sum A_p^2 with plain numpy, equals the mosaic (ducc0 + uvw rotation)."""
    from astropy.wcs import WCS

    from xstack.coords import SPEED_OF_LIGHT

    src = offset_position(9.0, 5.0)
    offsets = [(-12.0, 0.0), (12.0, 0.0), (0.0, 20.0)]
    parts, beam, freq = _alma_mosaic(1.0, src, offsets, noise=0.2, n_time=3, n_ant=6)
    write_store(parts, tmp_path / "m.zarr")
    size, cell = 48, 1.5
    res = make_image(tmp_path / "m.zarr", size=size, cell_arcsec=cell, epsilon=1e-9, pb_cutoff=0.05)
    assert res.header["XSMOSAIC"] == 3
    # the mosaic center: the mean direction of the pointings, at the reference pixel
    center = offset_position(0.0, 20.0 / 3)
    ra_c, dec_c = res.wcs.pixel_to_world_values(size // 2, size // 2)
    assert angular_separation_deg(ra_c, dec_c, *np.degrees(center)) * 3600 < 0.02
    # every pixel's sky direction from astropy's own WCS of the written file
    wcs = WCS(res.header).celestial
    yy, xx = np.mgrid[0:size, 0:size]
    ra, dec = (np.radians(a) for a in wcs.pixel_to_world_values(xx, yy))
    num = np.zeros((size, size))
    den = np.zeros((size, size))
    for ds in parts.values():
        ra0, dec0 = ds.attrs["phase_center"]
        l = np.cos(dec) * np.sin(ra - ra0)
        m = np.sin(dec) * np.cos(dec0) - np.cos(dec) * np.sin(dec0) * np.cos(ra - ra0)
        n1 = np.sqrt(1 - l * l - m * m) - 1
        uvw = ds.UVW.values.reshape(-1, 3)
        w = ds.WEIGHT.values.reshape(uvw.shape[0], freq.size, 2).sum(axis=-1)
        v = (ds.VISIBILITY.values * ds.WEIGHT.values).reshape(uvw.shape[0], freq.size, 2).sum(-1)
        d = np.zeros((size, size))
        for c, f in enumerate(freq):
            ph = (uvw[:, 0, None, None] * l + uvw[:, 1, None, None] * m
                  + uvw[:, 2, None, None] * n1) * (f / SPEED_OF_LIGHT)
            d += np.einsum("r,ryx->yx", v[:, c].real, np.cos(2 * np.pi * ph)) \
                + np.einsum("r,ryx->yx", v[:, c].imag, np.sin(2 * np.pi * ph))
        d /= w.sum()
        a = beam(np.arccos(np.clip(np.sin(dec) * np.sin(dec0)
                                   + np.cos(dec) * np.cos(dec0) * np.cos(ra - ra0), -1, 1)),
                 res.frequency)
        num += a * d
        den += a * a
    # coverage: the normalised effective beam sqrt(sum A_p^2) / its maximum >= the cutoff
    pb_expect = np.sqrt(den / 3) / np.sqrt(den / 3).max()
    expect = np.where(pb_expect >= 0.05, num / den, np.nan)
    assert np.array_equal(np.isnan(res.image), np.isnan(expect))
    ok = np.isfinite(expect)
    assert ok.sum() > 0.5 * ok.size
    assert np.max(np.abs(res.image[ok] - expect[ok])) < 1e-5 * np.nanmax(np.abs(expect))
    np.testing.assert_allclose(res.primary_beam, pb_expect, rtol=1e-6)  # equal pointing weights
    assert res.header["XSPBNORM"] == pytest.approx(np.sqrt(den / 3).max(), rel=1e-6)


def angular_separation_deg(ra1, dec1, ra2, dec2):
    from xstack.coords import angular_separation

    return np.degrees(angular_separation(*np.radians([ra1, dec1, ra2, dec2])))


def test_linear_mosaic_recovers_flux_between_pointings(tmp_path):
    """A source where each pointing sees it at ~half power: the mosaic shows its true flux at
    its catalog position, and pointings with more weight count more."""
    size, cell = 96, 0.5
    # put the source on a pixel center of the mosaic grid (center = mean of the pointings)
    offsets = [(-10.0, 0.0), (10.0, 0.0)]
    probe = make_image(_alma_mosaic(0.0, offset_position(0, 0), offsets)[0], size=size,
                       cell_arcsec=cell)
    ra, dec = probe.wcs.pixel_to_world_values(size // 2 - 6, size // 2 + 4)
    src = (math.radians(ra), math.radians(dec))
    parts, beam, freq = _alma_mosaic(0.05, src, offsets)
    # the second pointing has 4x the weight (half the noise) and sees a different flux if
    # its beam were wrong: a wrong weight or beam would not give 0.05
    w = parts["spw0_field1"].WEIGHT.values * 4
    parts["spw0_field1"] = parts["spw0_field1"].assign(WEIGHT=(parts["spw0_field1"].WEIGHT.dims, w))
    res = make_image(parts, size=size, cell_arcsec=cell)
    # away from the well-covered area 1/A amplifies the sidelobes: look where pb > 0.5
    y, x = np.unravel_index(np.nanargmax(np.where(res.primary_beam > 0.5, res.image, -np.inf)),
                            res.image.shape)
    assert (y, x) == (size // 2 + 4, size // 2 - 6)
    assert res.image[y, x] == pytest.approx(0.05, rel=1e-4)
    world = res.wcs.pixel_to_world(x, y)
    assert world.separation(SkyCoord(src[0] * u.rad, src[1] * u.rad)).arcsec < 0.01
    weights = [p["noise_weight"] for p in res.extra["pointings"]]
    assert weights[1] / weights[0] == pytest.approx(4.0, rel=1e-9)
    # each pointing alone sees the flux attenuated by its own beam at the source
    for name in ("spw0_field0", "spw0_field1"):
        single = make_image(parts, size=size, cell_arcsec=cell, partitions=name)
        sep = single.wcs.pixel_to_world(size // 2, size // 2).separation(world)
        att = float(np.mean(beam(sep.rad, freq)))
        assert 0.3 < att < 0.95
        # (each pointing's own grid is centered on it: find the source there)
        sx, sy = single.wcs.world_to_pixel(world)
        assert single.image[int(round(float(sy))), int(round(float(sx)))] == \
            pytest.approx(0.05 * att, rel=0.02)
    assert res.psf[size // 2, size // 2] == pytest.approx(1.0, abs=1e-6)
    # the flat-noise image is the mosaic times the effective beam
    ok = np.isfinite(res.image)
    np.testing.assert_allclose(res.extra["uncorrected"][ok], (res.image * res.primary_beam)[ok], rtol=1e-9)
    # NaN exactly where the effective beam (peak 1) is below the 0.1 cutoff
    assert res.primary_beam.max() == pytest.approx(1.0)
    assert np.isnan(res.image[res.primary_beam < 0.1]).all()
    assert np.isfinite(res.image[res.primary_beam >= 0.1]).all()
    assert np.isnan(res.image).any()


def test_mfs_over_spectral_windows_is_weighted_combination(tmp_path):
    src = offset_position(30.0, 20.0)
    a = make_sky_partition([(src[0], src[1], 1.0)], n_time=4, n_ant=8, freq0=1.3e9, noise=0.2)
    b = make_sky_partition([(src[0], src[1], 1.0)], n_time=4, n_ant=8, freq0=1.6e9, noise=0.4,
                           seed=5)
    b = b.assign_attrs(spectral_window_id=1)
    write_store({"spw0_field0": a, "spw1_field0": b}, tmp_path / "s.zarr")
    both = make_image(tmp_path / "s.zarr", size=64, cell_arcsec=3.0)
    ra = make_image(a, size=64, cell_arcsec=3.0)
    rb = make_image(b, size=64, cell_arcsec=3.0)
    expect = (ra.sum_weights * ra.image + rb.sum_weights * rb.image) / (ra.sum_weights + rb.sum_weights)
    assert np.allclose(both.image, expect, atol=1e-6)
    assert both.sum_weights == pytest.approx(ra.sum_weights + rb.sum_weights)
    assert ra.frequency < both.frequency < rb.frequency


def test_off_pixel_source_within_pixelisation_loss():
    """A source half a pixel off in RA and Dec peaks at the Gaussian-beam value of the offset."""
    cell = 3.0
    src = offset_position(-(10 + 0.5) * cell, (4 + 0.5) * cell)
    ds = make_sky_partition([(src[0], src[1], 1.0)], n_time=16, n_ant=10)
    res = make_image(ds, size=64, cell_arcsec=cell)
    y, x = np.unravel_index(np.argmax(res.image), res.image.shape)
    assert x - 32 in (10, 11) and y - 32 in (4, 5)  # west = right, north = up
    from xstack.imaging.kernels import gaussian_image

    bmaj, bmin, bpa = res.beam
    g = gaussian_image(64, 64, bmaj / cell, bmin / cell, bpa, center=(32 + 4.5, 32 + 10.5))
    expected = g[y, x]
    assert 0.8 < expected < 0.99
    assert res.image[y, x] == pytest.approx(expected, abs=0.02)
    assert res.image[y, x] < 1.0


@pytest.mark.slow
def test_type3_size_image_is_practical():
    """A 4000 x 4000 image (paper type 3: 30' at 0.45") with w-term, point source recovered."""
    import time

    src = offset_position(-400.0, 300.0)  # 8' off-center: the w-term matters
    ds = make_sky_partition([(src[0], src[1], 1.0)], n_time=60, n_ant=27, n_chan=4,
                            max_baseline=30000.0)
    t = time.perf_counter()
    res = make_image(ds, size=4000, cell_arcsec=0.45, epsilon=1e-5)
    assert time.perf_counter() - t < 600
    y, x = np.unravel_index(np.argmax(res.image), res.image.shape)
    world = res.wcs.pixel_to_world(x, y)
    assert world.separation(SkyCoord(src[0] * u.rad, src[1] * u.rad)).arcsec < 0.45
    assert res.image[y, x] > 0.9
