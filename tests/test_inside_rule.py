"""One rule for "inside the field" in every stage (issue 11 item 8, docs/conventions.md).

Truth from outside the code under test: the radius where the ALMA primary-beam model falls
to the cutoff at the highest channel frequency of the data, found by root finding on the
beam model (``PrimaryBeam.radius_at``). Positions are placed just inside (0.99 r) and just
outside (1.01 r) that radius, and in the shell between it and the (larger) cutoff radius at
the mean frequency, where the image's own beam (the reference frequency) used to admit them.
On simulated data with a wide band (87-113 GHz): uvstack, uv-domain noise (all four
methods), image -> imstack and image-domain noise (all four methods) must use exactly the
positions inside that radius: the same count and the same rows.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from astropy.io import fits

from xstack.beams import BAND_TOP_KEY, covered, inside_field, standard_beam
from xstack.imaging.image import make_image
from xstack.imstack.stack import stack_images
from xstack.noise.estimate import estimate_noise
from xstack.sim.presets import preset_dict
from xstack.sim.simulate import simulate, simulate_partitions
from xstack.uvstack.stack import stack_uv

#: radius / (cutoff radius at the highest channel) and position angle (deg) of each row
FRACTIONS = [0.3, 0.8, 0.99, 1.01, 1.06, 1.12, 0.6, 1.03]
ANGLES = [10.0, 100.0, 200.0, 300.0, 45.0, 135.0, 225.0, 315.0]
CENTER_GHZ, BANDWIDTH_GHZ, CHANNELS = 100.0, 40.0, 3


def _offsets_deg(ra0: float, dec0: float, r_arcsec: np.ndarray, pa_deg: np.ndarray):
    """Exact (ra, dec) at angular distance r and position angle pa (east of north)."""
    r, pa = np.radians(r_arcsec / 3600), np.radians(pa_deg)
    d0 = np.radians(dec0)
    dec = np.arcsin(np.sin(d0) * np.cos(r) + np.cos(d0) * np.sin(r) * np.cos(pa))
    dra = np.arctan2(np.sin(pa) * np.sin(r) * np.cos(d0), np.cos(r) - np.sin(d0) * np.sin(dec))
    return ra0 + np.degrees(dra), np.degrees(dec)


@pytest.fixture(scope="module")
def chain(tmp_path_factory):
    d = tmp_path_factory.mktemp("inside")
    scene = preset_dict("paper-8")  # ALMA 12 m antennas, here as one pointing
    ra0, dec0 = scene["pointings"]["center"]
    scene["pointings"] = {"mode": "single", "center": [ra0, dec0]}
    scene["spectral"].update(center=CENTER_GHZ * 1e9, bandwidth=BANDWIDTH_GHZ * 1e9,
                             channels=CHANNELS)
    scene["observation"].update(time_per_pointing=600.0, integration=60.0)
    scene["effects"]["noise"] = {"sigma": 0.05}
    scene["populations"] = []
    parts, _ = simulate_partitions(scene)
    freqs = np.asarray(next(iter(parts.values()))["frequency"].values, dtype=np.float64)
    assert freqs.size == CHANNELS
    # truth: the cutoff radius at the top channel, from the beam model by root finding
    beam = standard_beam("ALMA", 12.0)
    r_top = np.degrees(beam.radius_at(0.1, float(freqs.max()))) * 3600
    r_mean = np.degrees(beam.radius_at(0.1, float(freqs.mean()))) * 3600
    assert r_mean > 1.12 * r_top  # the shell rows are inside at the mean frequency
    ra, dec = _offsets_deg(ra0, dec0, np.array(FRACTIONS) * r_top, np.array(ANGLES))
    fluxes = 1e-3 * (1.0 + np.arange(len(FRACTIONS)))  # distinct: a stack tells its rows
    scene["populations"] = [{"name": f"s{k}", "count": 1,
                             "flux": {"kind": "fixed", "value": float(fluxes[k])},
                             "positions": {"kind": "list", "ra": [float(ra[k])],
                                           "dec": [float(dec[k])]},
                             "shape": {"kind": "point"}} for k in range(len(FRACTIONS))]
    store = d / "sim.zarr"
    simulate(scene, store)
    cat = d / "cat.csv"
    cat.write_text("ra,dec\n" + "".join(f"{a:.10f},{b:.10f}\n" for a, b in zip(ra, dec)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        img = make_image(str(store), size=320, cell_arcsec=0.5, epsilon=1e-5)
    out = d / "img.fits"
    img.write_with_pb(out)
    img.write(d / "img.psf.fits", img.psf, kind="psf")
    expected = np.flatnonzero(np.array(FRACTIONS) < 1.0)
    return {"store": str(store), "cat": str(cat), "image": out, "expected": expected,
            "freqs": freqs, "r_top": r_top, "fluxes": fluxes}


def test_rule_is_the_band_edge():
    """inside_field == "A >= cutoff in every channel" for the channels, and for the band."""
    beam = standard_beam("ALMA", 12.0)
    chans = np.array([86.7e9, 100e9, 113.3e9])
    theta = np.radians(np.linspace(0, 90, 901) / 3600)
    every = np.all(beam.main_lobe(theta[:, None], chans[None, :]) >= 0.1, axis=1)
    assert np.array_equal(inside_field(beam, theta, chans), every)
    assert np.array_equal(inside_field(beam, theta, (chans.min(), chans.max())), every)
    assert not covered(np.array([0.0]), 0.0)[0]  # beyond the null: outside even at cutoff 0


def test_image_records_its_band_edge(chain):
    with fits.open(chain["image"]) as h:
        assert h[0].header[BAND_TOP_KEY] == pytest.approx(float(chain["freqs"].max()), rel=1e-12)


def test_every_stage_admits_the_same_rows(chain):
    """Same count and same rows: uvstack's ``used`` and imstack's skipped rows are the rows
    inside the truth radius; every noise method reports that count, and its stacked target
    flux is that of the matching stack (same estimator, so equal only on the same rows)."""
    expected = chain["expected"]
    n = expected.size
    outside = sorted(set(range(len(FRACTIONS))) - set(expected))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = stack_uv(chain["store"], chain["cat"], out=None)
        st = stack_images(chain["image"], chain["cat"], stamp_size=33, skip_outside=True,
                     weighting="pb")
    used = np.asarray(res.positions["used"]).reshape(len(res.positions), -1).any(axis=1)
    assert np.array_equal(np.flatnonzero(used), expected)
    assert res.n_positions == n
    assert st.n_positions == n
    assert sorted(k - 1 for k in st.skipped_rows) == outside  # 1-based catalog rows
    rows_im = np.flatnonzero(np.asarray(st.weights).reshape(len(FRACTIONS), -1).any(axis=1))
    assert np.array_equal(rows_im, expected)
    # both stacks measure the true pb-weighted flux of the expected rows
    beam = standard_beam("ALMA", 12.0)
    ra0, dec0 = preset_dict("paper-8")["pointings"]["center"]
    theta = np.radians(np.array(FRACTIONS)[expected] * chain["r_top"] / 3600)
    a2 = beam(theta, float(chain["freqs"].mean())) ** 2
    truth = float(np.sum(a2 * chain["fluxes"][expected]) / np.sum(a2))
    assert abs(res.flux_jy - truth) < 5 * res.flux_err_jy
    assert abs(st.flux_jy - truth) < 5 * st.flux_err_jy

    for method in ("analytic", "bootstrap", "random", "mc"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            r = estimate_noise(chain["store"], chain["cat"], method=method, realizations=3,
                               flux=1e-3, seed=1)
            ri = estimate_noise(str(chain["image"]), chain["cat"], method=method,
                                realizations=3, flux=1e-3, seed=1, domain="image")
        assert (r.n_positions, ri.n_positions) == (n, n), method
        assert r.target_flux_jy == pytest.approx(res.flux_jy, rel=1e-6), method
        assert ri.target_flux_jy == pytest.approx(st.flux_jy, rel=1e-6), method


@pytest.mark.parametrize("pb", ["model", "file"])
def test_imstack_beam_given_explicitly_same_rows(chain, pb):
    """The rule holds whichever way the image's beam is given: a model or a beam image."""
    beam = standard_beam("ALMA", 12.0) if pb == "model" else \
        chain["image"].with_name("img.pb.fits")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        st = stack_images(chain["image"], chain["cat"], stamp_size=33, skip_outside=True, primary_beam=beam)
    assert sorted(k - 1 for k in st.skipped_rows) == \
        sorted(set(range(len(FRACTIONS))) - set(chain["expected"]))


def test_band_edge_of_a_third_party_image(chain):
    """Without XSFRQHI the band edge is the top of the frequency plane, CRVAL3 + CDELT3/2."""
    from xstack.imstack.io import read_image

    with fits.open(chain["image"]) as h:
        header = h[0].header.copy()
        data = h[0].data
    del header[BAND_TOP_KEY]
    header["CRVAL3"], header["CDELT3"] = 100e9, 20e9
    info = read_image(fits.PrimaryHDU(data, header=header))
    assert info.band_top_hz == pytest.approx(110e9)
    assert read_image(chain["image"]).band_top_hz == pytest.approx(float(chain["freqs"].max()))
