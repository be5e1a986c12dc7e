"""One primary-beam convention for image, imstack, image-domain noise and image fits.

Truth from outside the code under test: noise-free simulated ALMA data (``xstack.sim``) of a
single point source of known flux (100 uJy) per store, at several primary-beam gains (one
source per image, so no sidelobe confusion). The dirty PSF peaks at 1, so the value of a
point source at its position is its flux in Jy/beam: after image -> imstack (sub-pixel
alignment), -> image-domain noise, -> image fit, every stage must give 100 uJy for the
corrected and for the uncorrected image alike (docs/conventions.md, "Primary beams and
images").
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from astropy.io import fits

from xstack.beams import standard_beam
from xstack.cli import main
from xstack.coords import angular_separation
from xstack.fit.imfit import fit_image
from xstack.imaging.image import make_image
from xstack.imstack.stack import stack_images
from xstack.noise.estimate import estimate_noise
from xstack.sim.presets import preset_dict
from xstack.sim.simulate import simulate_partitions

FLUX = 100e-6
#: (east, north) arcsec offsets from the pointing: primary-beam gains ~0.97 to ~0.2 at 230 GHz,
#: on pixel centers of the 0.2" grid (image-domain noise stacks the nearest pixel)
OFFSETS = [(1.4, 1.8), (5.2, 7.0), (-7.4, 9.8), (9.2, -12.2), (-10.8, -14.6)]


def _scene(ra: float, dec: float, *, noise: bool = False) -> dict:
    d = preset_dict("paper-8")  # ALMA 230 GHz, the paper's mosaic type, as one pointing
    ra0, dec0 = d["pointings"]["center"]
    d["pointings"] = {"mode": "single", "center": [ra0, dec0]}
    if not noise:
        d["effects"].pop("noise")
    d["spectral"]["channels"] = 2
    d["observation"]["time_per_pointing"] = 600.0
    d["observation"]["integration"] = 60.0
    d["populations"] = [{"name": "targets", "count": 1, "flux": {"kind": "fixed", "value": FLUX},
                         "positions": {"kind": "list", "ra": [ra], "dec": [dec]},
                         "shape": {"kind": "point"}}]
    return d


def _position(dx: float, dy: float) -> tuple[float, float]:
    ra0, dec0 = preset_dict("paper-8")["pointings"]["center"]
    return ra0 + dx / 3600 / np.cos(np.radians(dec0)), dec0 + dy / 3600


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    """Per source: the position, its true gain and the uncorrected / corrected image files."""
    d = tmp_path_factory.mktemp("pbconv")
    beam = standard_beam("ALMA", 12.0)
    ra0, dec0 = preset_dict("paper-8")["pointings"]["center"]
    out = []
    for k, (dx, dy) in enumerate(OFFSETS):
        ra, dec = _position(dx, dy)
        parts, cats = simulate_partitions(_scene(ra, dec))
        parts = {n: v.compute() for n, v in parts.items()}  # imaging reads them more than once
        row = {"pos": np.array([[float(cats["targets"]["ra"][0]), float(cats["targets"]["dec"][0])]])}
        for pbcor in (False, True):
            res = make_image(parts, size=256, cell_arcsec=0.2, pbcor=pbcor, epsilon=1e-4)
            name = d / f"src{k}_{'pbcor' if pbcor else 'flat'}.fits"
            res.write_with_pb(name)
            res.write(name.with_name(name.name[:-5] + ".psf.fits"), res.psf, kind="psf")
            row["pbcor" if pbcor else "flat"] = name
            row["frequency"] = res.frequency
        theta = angular_separation(*np.radians([ra, dec, ra0, dec0]))
        row["gain"] = float(beam(theta, row["frequency"]))
        out.append(row)
    gains = [r["gain"] for r in out]
    assert max(gains) > 0.9 and min(gains) < 0.25  # the sources span the primary beam
    return out


def test_imstack_gives_the_injected_flux_on_corrected_and_uncorrected_images(images):
    for row in images:
        fluxes, weights = [], []
        for kind in ("flat", "pbcor"):
            res = stack_images(row[kind], row["pos"], stamp_size=32, subpixel="fourier", weighting="pb")
            fluxes.append(res.flux_jy)
            weights.append(res.weights[0, 0])
            used = res.primary_beam[0]
            assert used["image_corrected"] is (kind == "pbcor")
            assert used["corrected_from"] == "header"
            assert used["beam"].startswith("beam file ") and used["beam"].endswith(".pb.fits")
            assert res.to_dict()["flux_convention"] == "primary-beam corrected"
        # the flux of the source, whatever its gain: not 100 uJy x A
        np.testing.assert_allclose(fluxes, FLUX, rtol=0.02, err_msg=f"gain {row['gain']:.2f}")
        # pb weights are A^2 from the image's own beam, the same for both conventions
        assert weights[0] == pytest.approx(weights[1], rel=1e-9)
        # (the beam file is sampled at the nearest pixel: ~1 % at the steepest slope here)
        assert np.sqrt(weights[0]) == pytest.approx(row["gain"], rel=0.02)


def test_image_noise_target_flux_is_the_injected_flux(images):
    for row in images:
        for kind in ("flat", "pbcor"):
            res = estimate_noise(row[kind], tuple(row["pos"].T), method="analytic",
                                 domain="image")
            assert res.target_flux_jy == pytest.approx(FLUX, rel=0.02), (kind, row["gain"])
            assert res.extra["primary_beam"]["image_corrected"] is (kind == "pbcor")
            assert res.extra["primary_beam"]["corrected_from"] == "header"


def test_image_fit_of_the_stack_gives_the_injected_flux(images, tmp_path):
    for k, row in enumerate(images[1::2]):
        for kind in ("flat", "pbcor"):
            out = tmp_path / f"stack{k}_{kind}.fits"
            stack_images(row[kind], row["pos"], stamp_size=48, subpixel="fourier", weighting="none",
                    out=out, plot=False)
            assert fits.getheader(out)["STPBCOR"] is True
            fit = fit_image(out, model="point", fit_radius_arcsec=2.0)
            assert fit.flux_jy == pytest.approx(FLUX, rel=0.03), (kind, row["gain"])
            assert fit.extra["primary_beam"] == "corrected"


def _strip(src, dst):
    """A copy of an image whose header says nothing about its primary beam (third-party)."""
    with fits.open(src) as h:
        hdr = h[0].header.copy()
        data = h[0].data.copy()
    for key in ("XSPBCOR", "XSPBFILE", "XSPBCUT"):
        hdr.remove(key, ignore_missing=True)
    fits.PrimaryHDU(data, header=hdr).writeto(dst)
    return dst


def test_an_image_without_the_keyword_warns_and_the_result_says_what_was_assumed(images, tmp_path):
    row = images[3]  # gain ~0.35
    plain = _strip(row["flat"], tmp_path / "third_party.fits")
    with pytest.warns(UserWarning, match="XSPBCOR.*image_corrected="):
        res = stack_images(plain, row["pos"], stamp_size=32, subpixel="fourier", weighting="none")
    assert res.primary_beam[0]["corrected_from"] == "assumed"
    assert res.primary_beam[0]["image_corrected"] is True
    # used as is: the apparent flux (that is what "as if corrected" means for this image)
    assert res.flux_jy == pytest.approx(FLUX * row["gain"], rel=0.02)
    # stated: divided by the telescope's beam at the pointing (TELESCOP, FREQ), no warning
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = stack_images(plain, row["pos"], stamp_size=32, subpixel="fourier", weighting="none",
                      image_corrected=False)
    assert res.primary_beam[0]["corrected_from"] == "option"
    assert res.primary_beam[0]["beam"].startswith("model: airy")
    assert res.flux_jy == pytest.approx(FLUX, rel=0.02)
    # image-domain noise warns in the same way and records the assumption
    with pytest.warns(UserWarning, match="XSPBCOR"):
        nres = estimate_noise(plain, tuple(row["pos"].T), method="analytic", domain="image")
    assert nres.extra["primary_beam"]["corrected_from"] == "assumed"
    # a stamp without STPBCOR (not from xstack imstack): fitted as is, with a warning
    stamp = tmp_path / "stamp.fits"
    stack_images(row["flat"], row["pos"], stamp_size=48, subpixel="fourier", weighting="none",
            out=stamp, plot=False)
    with fits.open(stamp) as h:
        hdus = fits.HDUList([h[0].copy(), *(x.copy() for x in h[1:])])
    del hdus[0].header["STPBCOR"]
    hdus.writeto(tmp_path / "stamp_plain.fits")
    with pytest.warns(UserWarning, match="STPBCOR"):
        fit = fit_image(tmp_path / "stamp_plain.fits", model="point", fit_radius_arcsec=2.0)
    assert fit.extra["primary_beam"] == "not stated"


def test_explicit_options_win_over_the_header(images):
    row = images[2]  # gain ~0.5
    # primary_beam="none": A = 1, so the uncorrected image gives its apparent flux
    res = stack_images(row["flat"], row["pos"], stamp_size=32, subpixel="fourier", primary_beam="none")
    assert res.primary_beam[0]["beam"] == "none (A = 1)"
    assert res.flux_jy == pytest.approx(FLUX * row["gain"], rel=0.02)
    # image_corrected=False on a corrected image: warned, and divided once more (as asked)
    with pytest.warns(UserWarning, match="XSPBCOR = T"):
        res = stack_images(row["pbcor"], row["pos"], stamp_size=32, subpixel="fourier",
                      image_corrected=False)
    assert res.flux_jy == pytest.approx(FLUX / row["gain"], rel=0.02)
    # the old spelling pbcor=True is image_corrected=False
    res = stack_images(row["flat"], row["pos"], stamp_size=32, subpixel="fourier", pbcor=True)
    assert res.primary_beam[0]["corrected_from"] == "option"
    assert res.flux_jy == pytest.approx(FLUX, rel=0.02)


def test_cli_image_writes_the_beam_and_imstack_reads_it(tmp_path, capsys):
    import xstack

    ra, dec = _position(*OFFSETS[3])
    sim = xstack.simulate(_scene(ra, dec), tmp_path / "s.zarr")
    pos = sim.catalogs["targets"]
    pos.write(tmp_path / "targets.ecsv")
    for flag in ([], ["--pbcor"]):
        out = tmp_path / f"img{len(flag)}.fits"
        assert main(["image", str(tmp_path / "s.zarr"), str(out), "--size", "256", "--cell", "0.2",
                     "--json", "--no-progress", *flag]) == 0
        payload = json.loads(capsys.readouterr().out)
        assert payload["pb_corrected"] is bool(flag)
        pb_file = tmp_path / f"img{len(flag)}.pb.fits"
        assert payload["files"]["pb"] == str(pb_file) and pb_file.exists()
        h = fits.getheader(out)
        assert h["XSPBCOR"] is bool(flag) and h["XSPBFILE"] == pb_file.name
        hr = fits.getheader(tmp_path / f"img{len(flag)}.residual.fits")
        assert hr["XSPBCOR"] is False and hr["XSPBFILE"] == pb_file.name
        assert "XSPBCOR" not in fits.getheader(pb_file)
        assert main(["imstack", str(out), str(tmp_path / "targets.ecsv"),
                     str(tmp_path / f"st{len(flag)}.fits"), "--subpixel", "fourier",
                     "--stamp-size", "32", "--weighting", "pb", "--json", "--no-png"]) == 0
        st = json.loads(capsys.readouterr().out)
        assert st["flux_jy"] == pytest.approx(FLUX, rel=0.02)
        assert st["primary_beam"][0]["image_corrected"] is bool(flag)
        assert st["primary_beam"][0]["beam"] == f"beam file {pb_file.name}"
    # the stated option on the command line wins, and a missing beam file is a clear error
    assert main(["imstack", str(tmp_path / "img0.fits"), str(tmp_path / "targets.ecsv"),
                 str(tmp_path / "x.fits"), "--image-corrected", "yes", "--subpixel", "fourier",
                 "--stamp-size", "32", "--json", "--no-png"]) == 0
    st = json.loads(capsys.readouterr().out)
    assert st["primary_beam"][0]["corrected_from"] == "option"
    (tmp_path / "img0.pb.fits").unlink()
    assert main(["imstack", str(tmp_path / "img0.fits"), str(tmp_path / "targets.ecsv"),
                 str(tmp_path / "y.fits"), "--json", "--no-png"]) == 1
    assert "XSPBFILE" in capsys.readouterr().err
    assert not (tmp_path / "y.fits").exists()


def test_write_with_pb_is_all_or_nothing(tmp_path):
    from xstack.errors import XstackError

    parts, _ = simulate_partitions(_scene(*_position(*OFFSETS[0])))
    res = make_image({n: v.compute() for n, v in parts.items()}, size=64, cell_arcsec=0.4,
                     epsilon=1e-4)
    (tmp_path / "a.fits").write_bytes(b"keep")
    with pytest.raises(XstackError, match="exists"):
        res.write_with_pb(tmp_path / "a.fits")
    assert not (tmp_path / "a.pb.fits").exists()  # nothing written
    assert (tmp_path / "a.fits").read_bytes() == b"keep"
    files = res.write_with_pb(tmp_path / "a.fits", overwrite=True)
    assert fits.getheader(files["image"])["XSPBFILE"] == "a.pb.fits"
    np.testing.assert_allclose(np.squeeze(fits.getdata(files["pb"])), res.primary_beam, rtol=1e-6)
