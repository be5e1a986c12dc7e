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
    # 1.5 Jy source 24" east and 12" south of the phase centre; cells of 2" put it on a pixel
    src = offset_position(24.0, -12.0)
    return make_sky_partition([(src[0], src[1], 1.5)], n_time=16, n_ant=10), src


def test_dirty_image_peak_position_and_flux(point_partition):
    ds, src = point_partition
    res = make_image(ds, size=128, cell_arcsec=2.0)
    img = res.image
    y, x = np.unravel_index(np.argmax(img), img.shape)
    # east is to the left: x decreases by 12 pixels; south: y decreases by 6
    assert (y - 64, x - 64) == pytest.approx((-6, -12), abs=0)
    # the source sits within 0.03 pixel of the pixel centre (SIN vs offsets): ~no pixel loss
    assert img[y, x] == pytest.approx(1.5, rel=1e-3)
    assert res.psf[64, 64] == pytest.approx(1.0, abs=1e-6)
    assert res.psf.max() == pytest.approx(1.0, abs=1e-6)
    # WCS: the brightest pixel's world position is the source (within 0.1 pixel)
    ra, dec = res.wcs.pixel_to_world_values(x, y)
    sep = SkyCoord(ra * u.deg, dec * u.deg).separation(SkyCoord(src[0] * u.rad, src[1] * u.rad))
    assert sep.arcsec < 0.2
    # and the phase centre is at the reference pixel
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
    assert b.pb is not None and 0.3 < b.pb[y, x] < 0.99
    assert b.image[y, x] == pytest.approx(a.image[y, x] / b.pb[y, x], rel=1e-9)
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


def test_mosaic_and_bad_input_errors(tmp_path):
    a = make_sky_partition(n_time=2, n_ant=4, field_id=0)
    b = make_sky_partition(n_time=2, n_ant=4, field_id=1,
                           phase_center=(PHASE_CENTER[0] + 1e-4, PHASE_CENTER[1]))
    path = tmp_path / "m.zarr"
    write_store({"spw0_field0": a, "spw0_field1": b}, path)
    with pytest.raises(XstackError, match="different phase centres"):
        make_image(path, size=32, cell_arcsec=1.0)
    r = make_image(path, size=32, cell_arcsec=1.0, partitions="*field1")
    assert r.partitions == ("spw0_field1",)
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
    g = gaussian_image(64, 64, bmaj / cell, bmin / cell, bpa, centre=(32 + 4.5, 32 + 10.5))
    expected = g[y, x]
    assert 0.8 < expected < 0.99
    assert res.image[y, x] == pytest.approx(expected, abs=0.02)
    assert res.image[y, x] < 1.0


@pytest.mark.slow
def test_type3_size_image_is_practical():
    """A 4000 x 4000 image (paper type 3: 30' at 0.45") with w-term, point source recovered."""
    import time

    src = offset_position(-400.0, 300.0)  # 8' off-centre: the w-term matters
    ds = make_sky_partition([(src[0], src[1], 1.0)], n_time=60, n_ant=27, n_chan=4,
                            max_baseline=30000.0)
    t = time.perf_counter()
    res = make_image(ds, size=4000, cell_arcsec=0.45, epsilon=1e-5)
    assert time.perf_counter() - t < 600
    y, x = np.unravel_index(np.argmax(res.image), res.image.shape)
    world = res.wcs.pixel_to_world(x, y)
    assert world.separation(SkyCoord(src[0] * u.rad, src[1] * u.rad)).arcsec < 0.45
    assert res.image[y, x] > 0.9
