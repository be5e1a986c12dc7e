"""The reproduction report (``xstack.reproduce.report``, ``xstack reproduce --report-only``).

A synthetic run directory — realisation lines with known numbers, one stamp file — so the
test runs nothing and takes seconds. The truth is from outside the code under test: the
table's numbers against plain numpy on the same values, the paper's columns against the text
of Table 2 typed here as literals, the mask radius against an analytic Gaussian PSF.
"""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

from xstack.errors import NoDataError
from xstack.reproduce import report as rp
from xstack.reproduce.run import JSONL, PROFILE_EDGES_KLAMBDA

NB = len(PROFILE_EDGES_KLAMBDA) - 1
PROC = {"size": 100}  # any procedure: the report only groups the lines by it


def _records(n, r, true, uv, im, rng, scale=0.05, **extra):
    out = []
    for k in range(r):
        rec = {"seed": k, "type": n, "scale": scale, "procedure": PROC, "true_flux_jy": true,
               "uv_flux_jy": float(uv[k]), "image_flux_jy": float(im[k]),
               "expected_noise_jy": 0.4e-6 + 0.01e-6 * k, "seconds": 10.0 + k,
               "image_stack_flux_err_jy": 0.45e-6 + 0.03e-6 * k,
               "profile": {"re_jy": [float(x) for x in true + 1e-6 * rng.normal(size=NB)],
                           "sum_weight": [1.0] * NB}}
        for key, values in extra.items():
            rec[key] = values[k]
        out.append(rec)
    return out


def _write(outdir, n, records, lines_before=()):
    d = outdir / f"type{n}"
    d.mkdir(parents=True, exist_ok=True)
    with open(d / JSONL, "w", encoding="utf-8") as f:
        for rec in [*lines_before, *records]:
            f.write(json.dumps(rec) + "\n")
        f.write('{"seed": 99, "trunc')  # an interrupted write: skipped
    return d


def _gauss_psf(size, fwhm_x_pix, fwhm_y_pix):
    y, x = np.mgrid[:size, :size] - size // 2
    sx, sy = (f / (2 * math.sqrt(2 * math.log(2))) for f in (fwhm_x_pix, fwhm_y_pix))
    return np.exp(-0.5 * ((x / sx) ** 2 + (y / sy) ** 2))


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    rng = np.random.default_rng(1)
    data = {}
    # type 1: 6 µJy targets, 8 realisations; an earlier line at another scale is left out
    uv, im = 6e-6 + 0.4e-6 * rng.normal(size=8), 5.9e-6 + 0.5e-6 * rng.normal(size=8)
    old = _records(1, 1, 6e-6, [1.0], [1.0], rng, scale=0.5)
    sub = im + 0.1e-6 + 0.02e-6 * rng.normal(size=8)
    data[1] = _records(1, 8, 6e-6, uv, im, rng, image_flux_subpixel_jy=list(sub))
    d = _write(out, 1, data[1], lines_before=old)
    np.savez_compressed(d / "stamp_seed0.npz", stamp=1e-6 * rng.normal(size=(64, 64)),
                        psf=_gauss_psf(64, 10, 20), pixel_arcsec=np.array([0.25, 0.25]))
    # type 6: with the target subsets (Fig. 1) and the filtered image flux (Fig. 12)
    r6 = 6
    uv, im = 1e-6 + 0.15e-6 * rng.normal(size=r6), 0.9e-6 + 0.18e-6 * rng.normal(size=r6)
    subsets = [{str(nn): float(1e-6 + 5e-6 / math.sqrt(nn) * rng.normal())
                for nn in (10, 30, 100, 300)} for _ in range(r6)]
    filt = list(0.95e-6 + 0.15e-6 * rng.normal(size=r6))
    data[6] = _records(6, r6, 0.99e-6, uv, im, rng, uv_flux_subsets_jy=subsets,
                       image_flux_filtered_jy=filt)
    _write(out, 6, data[6])
    # type 7: fitted sizes, one failed uv fit; a stamp with its filtered version
    r7 = 5
    uv, im = 3e-6 + 0.4e-6 * rng.normal(size=r7), 3e-6 + 0.5e-6 * rng.normal(size=r7)
    uvf = [1.5, 1.3, None, 1.7, 1.6]
    imf = list(1.55 + 0.4 * rng.normal(size=r7))
    data[7] = _records(7, r7, 2.96e-6, uv, im, rng, uv_fwhm_arcsec=uvf, image_fwhm_arcsec=imf)
    data[7][2]["uv_flux_jy"] = None  # the failed fit has no flux either
    d = _write(out, 7, data[7])
    np.savez_compressed(d / "stamp_seed0.npz", stamp=1e-6 * rng.normal(size=(32, 32)),
                        psf=_gauss_psf(32, 6, 6), pixel_arcsec=np.array([0.5, 0.5]),
                        stamp_filtered=1e-6 * rng.normal(size=(32, 32)))
    # type 9: an ALMA type, in mJy
    uv, im = 1e-3 + 0.08e-3 * rng.normal(size=4), 0.97e-3 + 0.09e-3 * rng.normal(size=4)
    data[9] = _records(9, 4, 1e-3, uv, im, rng)
    _write(out, 9, data[9])
    md = rp.write_report(out)
    return out, data, md, md.read_text(encoding="utf-8")


def _row(text, n):
    line = next(x for x in text.splitlines() if x.startswith(f"| {n} |"))
    return [c.strip() for c in line.strip("|").split("|")]


def _pm(values, unit, snr=True):
    v = np.asarray([x for x in values if x is not None], float)
    m, s = v.mean(), v.std(ddof=1)
    out = f"{m / unit:.2f} ± {s / unit:.2f}"
    return out + f" ({m / s:.1f})" if snr else out


def test_table_is_plain_numpy_of_the_lines(run_dir):
    out, data, md, text = run_dir
    assert md == out / "report.md"
    for n, unit, label in ((1, 1e-6, "µJy"), (6, 1e-6, "µJy"), (7, 1e-6, "µJy"),
                           (9, 1e-3, "mJy")):
        recs = data[n]
        row = _row(text, n)
        assert row[0:4] == [str(n), str(len(recs)), "0.05", label]
        noise = np.mean([r["expected_noise_jy"] for r in recs])
        assert row[4] == f"{recs[0]['true_flux_jy'] / unit:.2f} ± {noise / unit:.2f}"
        uv = [r["uv_flux_jy"] for r in recs]
        assert row[5] == _pm(uv, unit)
        assert row[6] == _pm([r["image_flux_jy"] for r in recs], unit)
        v = np.asarray([x for x in uv if x is not None], float)
        off = (v.mean() - recs[0]["true_flux_jy"]) / (v.std(ddof=1) / math.sqrt(v.size))
        assert row[10] == f"{off:+.1f}"
        assert row[11] == f"{np.mean([r['seconds'] for r in recs]):.1f}"
    # the numbers themselves, not only their print
    t = rp.type_numbers(1, data[1])
    uv = np.array([r["uv_flux_jy"] for r in data[1]])
    assert t["uv_flux_mean_jy"] == pytest.approx(uv.mean(), rel=1e-12)
    assert t["uv_flux_scatter_jy"] == pytest.approx(uv.std(ddof=1), rel=1e-12)
    assert t["uv_snr"] == pytest.approx(uv.mean() / uv.std(ddof=1), rel=1e-12)
    assert t["uv_offset_se"] == pytest.approx((uv.mean() - 6e-6) / (uv.std(ddof=1) / 8 ** 0.5),
                                              rel=1e-12)
    assert t["seconds"] == pytest.approx(sum(10.0 + k for k in range(8)))


def test_paper_columns_are_table_2(run_dir):
    text = run_dir[3]
    # Table 2 of Lindroos et al. 2015, typed from the paper
    assert _row(text, 1)[7:10] == ["6.00 ± 0.47", "6.02 ± 0.38 (15.8)", "5.89 ± 0.49 (12.0)"]
    assert _row(text, 6)[7:10] == ["0.99 ± 0.15", "0.99 ± 0.16 (6.2)", "0.91 ± 0.18 (5.1)"]
    assert _row(text, 7)[7:10] == ["2.96", "2.96 ± 0.41 (7.2)", "3.01 ± 0.54 (5.6)"]
    assert _row(text, 9)[7:10] == ["1.00 ± 0.09", "1.00 ± 0.08 (12.5)", "0.97 ± 0.09 (10.8)"]


def test_type7_sizes_and_failed_fits(run_dir):
    out, data, md, text = run_dir
    uv = np.array([r["uv_fwhm_arcsec"] for r in data[7] if r["uv_fwhm_arcsec"] is not None])
    im = np.array([r["image_fwhm_arcsec"] for r in data[7]])
    line = next(x for x in text.splitlines() if x.startswith("| uv fit |"))
    assert f"| 4 of 5 | {uv.mean():.2f} ± {uv.std(ddof=1):.2f} | 1.50 ± 0.21 |" in line
    line = next(x for x in text.splitlines() if x.startswith("| image fit"))
    assert f"| 5 of 5 | {im.mean():.2f} ± {im.std(ddof=1):.2f} | 1.55 ± 0.43 |" in line


def test_other_scale_and_truncated_lines_left_out(run_dir):
    text = run_dir[3]
    assert ("Type 1: 1 line(s) made at another scale, with another procedure or from another "
            "scene left out") in text


def _png_ok(path):
    raw = path.read_bytes()
    assert raw[:8] == b"\x89PNG\r\n\x1a\n" and raw[12:16] == b"IHDR"
    w, h = int.from_bytes(raw[16:20], "big"), int.from_bytes(raw[20:24], "big")
    assert w > 100 and h > 100


def test_every_figure_is_a_png_referenced_with_a_caption(run_dir):
    out, data, md, text = run_dir
    links = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text)
    expected = {"flux_type1", "flux_type6", "flux_type7", "flux_type9", "stamp_type1",
                "stamp_type7", "uvprofile_type1", "uvprofile_type6", "uvprofile_type7",
                "uvprofile_type9", "sizes_type7", "noise_vs_targets", "filtered_type6"}
    assert {p.rsplit("/", 1)[-1][:-4] for p in links} == expected
    assert {p.stem for p in (out / "figures").glob("*.png")} == expected
    for link in links:
        assert link.startswith("figures/")  # relative to the markdown
        _png_ok(md.parent / link)
    # each figure is followed by its caption naming the paper's figure
    assert text.count("*Figure ") == len(expected)
    assert "Figs 2, 6" in text and "Fig. 3" in text and "Figs 5, 7, 9, 10" in text
    assert "Fig. 8" in text and "Fig. 1:" in text and "Fig. 12" in text
    assert "short baselines filtered out" in text  # type 7's stamp has its filtered panel
    skipped = text.split("Figures skipped")[1].strip().splitlines()[2:]
    assert [x.split(":")[0] for x in skipped] == [
        "- The paper's Fig. 3 (stacked stamp), type 6", "- The paper's Fig. 3 (stacked stamp), type 9"]


def test_absent_data_skip_their_figures(tmp_path):
    rng = np.random.default_rng(2)
    recs = _records(2, 3, 6e-6, [6e-6, 6.2e-6, 5.7e-6], [5.7e-6, 5.9e-6, 5.5e-6], rng)
    for r in recs:
        del r["profile"]
    _write(tmp_path, 2, recs)
    md = rp.write_report(tmp_path, out_md=tmp_path / "docs" / "page.md",
                         figures_dir=tmp_path / "docs" / "img")
    text = md.read_text(encoding="utf-8")
    assert re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text) == ["img/flux_type2.png"]
    _png_ok(tmp_path / "docs" / "img" / "flux_type2.png")
    skipped = text.split("Figures skipped")[1]
    for what in ("Fig. 3 (stacked stamp), type 2", "Figs 5, 7, 9, 10 (uv-profile), type 2",
                 "Fig. 1 (noise against number of targets)", "Fig. 12 (filtered image stacks)"):
        assert what in skipped
    assert not (tmp_path / "report.md").exists()


def test_noise_by_count_and_profile_mean(run_dir):
    out, data, md, text = run_dir
    by = rp.noise_by_count(data[6])
    assert sorted(by) == [10, 30, 100, 300]
    for nn, (count, std) in by.items():
        v = np.array([r["uv_flux_subsets_jy"][str(nn)] for r in data[6]])
        assert count == 6 and std == pytest.approx(v.std(ddof=1), rel=1e-12)
    prof = rp.profile_matrix(data[1], NB)
    raw = np.array([r["profile"]["re_jy"] for r in data[1]])
    mean, err, counts = rp.profile_stats(prof)
    np.testing.assert_allclose(mean, raw.mean(axis=0), rtol=1e-12)
    np.testing.assert_allclose(err, raw.std(axis=0, ddof=1) / np.sqrt(8), rtol=1e-12)
    assert (counts == 8).all()


def test_mask_radius_from_an_analytic_psf():
    # the default mask radius is the beam's major FWHM: 20 pixels of 0.25" = 5"
    assert rp.psf_mask_radius(_gauss_psf(64, 10, 20), 0.25) == pytest.approx(5.0, abs=0.25)
    assert math.isnan(rp.psf_mask_radius(np.zeros(0), 0.25))


def test_size_histogram_has_no_bin_below_zero():
    # a fit that collapsed to a point (FWHM 0) used to open a bin at -0.2"; every value still
    # falls inside the edges, and without the floor the edges pad below the smallest value
    sizes = [np.array([0.0, 1.2, 1.5, 2.1]), np.array([1.5])]
    edges = rp._bins(sizes, floor=0.0)
    assert edges[0] == 0.0 and edges[-1] > 2.1
    counts, _ = np.histogram(np.concatenate(sizes), bins=edges)
    assert counts.sum() == 5
    assert rp._bins(sizes)[0] < 0.0


def test_no_realisations_is_an_error(tmp_path):
    with pytest.raises(NoDataError, match="no realisations"):
        rp.write_report(tmp_path / "missing")
    assert not (tmp_path / "missing").exists()


def test_cli_report_only(run_dir, tmp_path, capsys):
    from xstack.cli import main

    out = run_dir[0]
    (out / "report.md").unlink()
    assert main(["reproduce", "--report-only", "--outdir", str(out), "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == {"report": str(out / "report.md")}
    assert (out / "report.md").read_text(encoding="utf-8") == run_dir[3]
    for missing in (tmp_path, tmp_path / "nothing"):
        assert main(["reproduce", "--report-only", "--outdir", str(missing)]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: no realisations in")
    assert main(["reproduce", "--outdir", str(tmp_path)]) == 1
    assert "--type is required" in capsys.readouterr().err


def test_ratios_table_is_plain_numpy(run_dir):
    """The paper's findings as ratios, type 1: xstack's from the lines, the paper's from the
    text of Table 2 (uv 6.02 ± 0.38 (15.8), image 5.89 (12.0))."""
    _, data, _, text = run_dir
    block = text.split("The paper's findings as ratios", 1)[1]
    row = next(x for x in block.splitlines() if x.startswith("| 1 |"))
    row = [c.strip() for c in row.strip("|").split("|")]
    recs = data[1]
    uv = np.array([r["uv_flux_jy"] for r in recs])
    im = np.array([r["image_flux_jy"] for r in recs])
    sub = np.array([r["image_flux_subpixel_jy"] for r in recs])
    off = (uv.mean() - 6e-6) / (uv.std(ddof=1) / math.sqrt(uv.size))
    snr = lambda a: a.mean() / a.std(ddof=1)  # noqa: E731
    assert row == ["1", "8", f"{off:+.1f}", f"{uv.std(ddof=1) / 0.38e-6:.2f}",
                   f"{im.mean() / uv.mean():.3f}", f"{5.89 / 6.02:.3f}",
                   f"{sub.mean() / uv.mean():.3f}", f"{snr(uv) / snr(im):.2f}",
                   f"{15.8 / 12.0:.2f}"]


def test_noise_table_is_plain_numpy(run_dir):
    """Expected noise two ways (thermal, map eq. 9) beside the paper's and the scatters."""
    _, data, _, text = run_dir
    block = text.split("thermal and from the residual map", 1)[1]
    row = next(x for x in block.splitlines() if x.startswith("| 1 |"))
    row = [c.strip() for c in row.strip("|").split("|")]
    recs = data[1]
    col = lambda k: np.array([r[k] for r in recs]) / 1e-6  # noqa: E731
    thermal, mapn = col("expected_noise_jy").mean(), col("image_stack_flux_err_jy").mean()
    uv, im = col("uv_flux_jy").std(ddof=1), col("image_flux_jy").std(ddof=1)
    assert row == ["1", "8", "µJy", f"{thermal:.3f}", f"{mapn:.3f}", "0.470", f"{uv:.3f}",
                   f"{im:.3f}", f"{uv / mapn:.2f}", f"{uv / thermal:.2f}"]


def _paired_row(text, n):
    block = text.split("same realisations", 1)[1]
    line = next(x for x in block.splitlines() if x.startswith(f"| {n} |"))
    return [c.strip() for c in line.strip("|").split("|")]


def test_paired_table_is_plain_numpy(run_dir):
    """image - uv per realisation, its standard error and the ratio of means, for the
    nearest-pixel and the sub-pixel image stacks; types without sub-pixel fluxes say n/a."""
    _, data, _, text = run_dir
    recs = data[1]
    uv = np.array([r["uv_flux_jy"] for r in recs])
    for key, cols in (("image_flux_jy", slice(2, 5)), ("image_flux_subpixel_jy", slice(5, 8))):
        im = np.array([r[key] for r in recs])
        d = (im - uv) / 1e-6
        se = d.std(ddof=1) / math.sqrt(d.size)
        assert _paired_row(text, 1)[cols] == [str(d.size), f"{d.mean():+.3f} ({se:.3f})",
                                              f"{im.mean() / uv.mean():.4f}"]
    # type 7's failed uv fit (None) is left out of the pairs; no sub-pixel fluxes
    uv7 = [r["uv_flux_jy"] for r in data[7]]
    assert _paired_row(text, 7)[2] == str(sum(x is not None for x in uv7))
    assert _paired_row(text, 7)[5:8] == ["0", "n/a", "n/a"]
    assert _paired_row(text, 9)[1] == "mJy"
