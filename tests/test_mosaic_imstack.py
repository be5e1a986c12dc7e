"""Image-stacking and image-domain noise on a linear mosaic: its effective beam travels with it.

A paper-8-like ALMA mosaic (230 GHz, hexagonal pointings 20" apart, here 4 of them). Targets
lie out to ~30" from the mosaic center, where a single-dish beam centered on the image is
below 1 %, but inside the mosaic. Truth from outside the code: the injected flux (noise-free
data, one source per mosaic so that no sidelobe confuses it), and for the noise the
analytic expectation from the visibility noise: a dirty pointing p has pixel variance
sigma^2 / N_p (natural weighting, N_p unflagged parallel-hand samples, each of noise sigma
per real part), the linear mosaic 1 / sum_p W_p A_p^2 with W_p = N_p / sigma^2, and the
A^2-weighted stack of K well separated positions 1 / sum_k sum_p W_p A_p(x_k)^2.
"""

from __future__ import annotations

import numpy as np
import pytest
from astropy.io import fits

from xstack.beams import standard_beam
from xstack.coords import angular_separation
from xstack.imaging.image import make_image
from xstack.imstack.stack import stack_images
from xstack.noise.estimate import estimate_noise
from xstack.sim.presets import preset_dict
from xstack.sim.simulate import simulate_partitions

FLUX = 100e-6
SIZE, CELL = 320, 0.25
#: (east, north) arcsec from the mosaic center, on pixel centers of its grid
TARGETS = [(0.0, 0.0), (21.0, 4.0), (-2.0, 29.0), (-19.0, -20.0), (12.0, -27.0)]


def _mosaic_scene(targets, noise: float | None = None) -> dict:
    d = preset_dict("paper-8")
    d["pointings"]["size_arcsec"] = [40.0, 40.0]   # 4 hexagonal pointings, 20" apart
    d["effects"].pop("noise")
    if noise is not None:
        d["effects"]["noise"] = {"sigma": noise}
    d["spectral"]["channels"] = 2
    d["observation"]["time_per_pointing"] = 300.0
    d["observation"]["integration"] = 60.0
    ra, dec = zip(*(_position(*t) for t in targets))
    d["populations"] = [{"name": "targets", "count": len(targets),
                         "flux": {"kind": "fixed", "value": FLUX if noise is None else 0.0},
                         "positions": {"kind": "list", "ra": list(ra), "dec": list(dec)},
                         "shape": {"kind": "point"}}]
    return d


def _position(dx: float, dy: float) -> tuple[float, float]:
    ra0, dec0 = preset_dict("paper-8")["pointings"]["center"]
    return ra0 + dx / 3600 / np.cos(np.radians(dec0)), dec0 + dy / 3600


def _simulate(scene: dict, seed: int = 0):
    """The partitions in memory (imaging reads them chunk by chunk, more than once)."""
    parts, cats = simulate_partitions(scene, seed=seed)
    return {k: v.compute() for k, v in parts.items()}, cats


def _write(res, path):
    """The files ``xstack image`` writes for a mosaic: image, beam, flat residual, PSF."""
    files = res.write_with_pb(path)
    resid = path.with_name(path.name[:-5] + ".residual.fits")
    res.write(resid, res.extra["uncorrected"], kind="residual", pb_file=files["pb"].name)
    res.write(path.with_name(path.name[:-5] + ".psf.fits"), res.psf, kind="psf")
    return files["image"], resid


@pytest.fixture(scope="module")
def mosaics(tmp_path_factory):
    d = tmp_path_factory.mktemp("mosaic")
    out = []
    for k, t in enumerate(TARGETS):
        parts, cats = _simulate(_mosaic_scene([t]))
        assert len(parts) == 4
        res = make_image(parts, size=SIZE, cell_arcsec=CELL, epsilon=1e-4)
        image, resid = _write(res, d / f"mosaic{k}.fits")
        pos = np.array([[float(cats["targets"]["ra"][0]), float(cats["targets"]["dec"][0])]])
        out.append({"image": image, "residual": resid, "pos": pos, "res": res})
    return out


def test_every_target_is_inside_the_mosaic_and_stacks_to_its_flux(mosaics):
    beam = standard_beam("ALMA", 12.0)
    first = mosaics[0]["res"]
    allpos = np.concatenate([m["pos"] for m in mosaics])
    # a beam centered on the image would put most targets outside (the reported bug)
    gain_center = beam(angular_separation(*np.radians(allpos.T), *first.phase_center),
                       first.frequency)
    assert (gain_center < 0.1).sum() >= 3
    # all targets are inside the mosaic: its effective beam covers them
    res = stack_images(mosaics[0]["image"], allpos, stamp_size=32, weighting="pb")
    assert res.n_positions == len(TARGETS) and res.skipped_rows == []
    assert res.primary_beam[0]["beam"] == "beam file mosaic0.pb.fits"
    # each source's flux, from the corrected mosaic and from its flat-noise residual alike
    for m in mosaics:
        for kind in ("image", "residual"):
            r = stack_images(m[kind], m["pos"], stamp_size=32, subpixel="fourier", weighting="pb")
            assert r.primary_beam[0]["image_corrected"] is (kind == "image")
            assert r.flux_jy == pytest.approx(FLUX, rel=0.02), (kind, m["pos"])
            n = estimate_noise(m[kind], tuple(m["pos"].T), method="analytic", domain="image")
            assert n.target_flux_jy == pytest.approx(FLUX, rel=0.02), (kind, m["pos"])


def test_the_effective_beam_is_the_noise_of_the_corrected_mosaic(mosaics):
    """pb = sqrt(sum W_p A_p^2) / max: the corrected mosaic's noise is sigma_flat / pb."""
    res = mosaics[0]["res"]
    w = np.array([p["noise_weight"] for p in res.extra["pointings"]])
    beam = standard_beam("ALMA", 12.0)
    ra, dec = (np.radians(a) for a in res.wcs.pixel_to_world_values(
        *np.meshgrid(np.arange(SIZE), np.arange(SIZE))))
    den = sum(wp * beam(angular_separation(ra, dec, *p["phase_center"]), res.frequency) ** 2
              for wp, p in zip(w, res.extra["pointings"]))
    np.testing.assert_allclose(res.primary_beam, np.sqrt(den) / np.sqrt(den).max(), rtol=1e-6, atol=1e-9)
    with fits.open(mosaics[0]["image"].with_name("mosaic0.pb.fits")) as h:
        np.testing.assert_allclose(np.squeeze(h[0].data), res.primary_beam, rtol=1e-6, atol=1e-7)


def test_image_noise_on_a_mosaic_matches_the_analytic_expectation(tmp_path):
    sigma = 1.0
    parts, cats = _simulate(_mosaic_scene(TARGETS, noise=sigma), seed=4)
    res = make_image(parts, size=SIZE, cell_arcsec=CELL, epsilon=1e-4)
    image, resid = _write(res, tmp_path / "noisy.fits")
    beam = standard_beam("ALMA", 12.0)
    ra_t, dec_t = np.radians(cats["targets"]["ra"]), np.radians(cats["targets"]["dec"])
    inv_var = np.zeros(len(TARGETS))
    for ds in parts.values():
        pol = [str(p) for p in ds["polarization"].values]
        par = [i for i, p in enumerate(pol) if p in ("XX", "YY")]
        n_p = int((~ds["FLAG"].values[..., par] & (ds["WEIGHT"].values[..., par] > 0)).sum())
        a = beam(angular_separation(ra_t, dec_t, *ds.attrs["phase_center"]), res.frequency)
        inv_var += n_p / sigma**2 * a**2
    expected = 1.0 / np.sqrt(inv_var.sum())
    for path in (image, resid):
        n = estimate_noise(path, (cats["targets"]["ra"], cats["targets"]["dec"]),
                           method="analytic", domain="image")
        assert n.n_positions == len(TARGETS)
        # sigma_map is a MAD over ~2000 independent beams of the flat image: a few % scatter
        assert n.noise_jy == pytest.approx(expected, rel=0.1), path.name
