"""``xstack reproduce``: the paper's Table 2 chain over realisations, resumable, and its JSON.

Two cheap types (1 and 2: one bright source, 25 targets) at a tiny scale with 2
realisations, on a small image (the paper's 1440 x 1440 / 720 x 720 pixels would make the
test slow; the image size is a procedure knob). The truth is from outside the code: the
injected flux is the paper's 6 µJy (Table 1), the paper's numbers are checked against the
text of Table 2 typed here as literals, means and scatters against plain numpy on the lines
of the JSONL file.
"""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
import warnings

import numpy as np
import pytest

from xstack.errors import OptionError, WeightsWarning, XstackWarning
from xstack.reproduce import paper
from xstack.reproduce import run as rr

SCALE = 0.005
TYPES = (1, 2)
#: a 6' field as the paper's type 1/2 images, with type 2's pixels twice type 1's as in the
#: paper but each twice the paper's (0.5" and 1", 6 and 3 px per beam): fast
SMALL = {n: dataclasses.replace(paper.PROCEDURES[n], cell_arcsec=cell, size=round(360 / cell))
         for n, cell in ((1, 0.5), (2, 1.0))}
KEYS = {"type", "realizations", "scale", "true_flux_jy", "uv_flux_mean_jy", "uv_flux_scatter_jy",
        "image_flux_mean_jy", "image_flux_scatter_jy", "expected_noise_jy", "expected_map_noise_jy",
        "paper", "seconds"}


@pytest.fixture(scope="module")
def first(tmp_path_factory):
    out = tmp_path_factory.mktemp("reproduce")
    res = rr.reproduce(list(TYPES), realizations=2, scale=SCALE, outdir=out, procedures=SMALL)
    return out, res, json.loads(json.dumps(res.to_dict()))


def _lines(out, n):
    return [json.loads(x) for x in (out / f"type{n}" / rr.JSONL).read_text().splitlines()]


def test_json_keys_counts_and_truth(first):
    out, res, d = first
    assert [t["type"] for t in d["types"]] == list(TYPES)
    for t in d["types"]:
        assert KEYS <= set(t)
        assert t["realizations"] == 2 and t["scale"] == SCALE
        # Table 1 / §2.2.1: 25 point sources of 6 µJy
        assert t["true_flux_jy"] == pytest.approx(6e-6, rel=1e-12)
        for k in ("uv_flux_mean_jy", "uv_flux_scatter_jy", "image_flux_mean_jy",
                  "image_flux_scatter_jy", "expected_noise_jy", "seconds"):
            assert t[k] is not None and math.isfinite(t[k]), k
        # a detection-level stack: within 5 expected sigma of the truth
        for k in ("uv_flux_mean_jy", "image_flux_mean_jy"):
            assert abs(t[k] - 6e-6) < 5 * t["expected_noise_jy"], (k, t[k])


def test_expected_noise_is_that_of_the_stack_weights(first):
    """The expected noise is the analytic noise (eq. 9) of the estimator that made the uv
    flux: the stack's own 1/sigma_k^2 position weights, passed to estimate_noise as a
    column. Two code paths: the stack's error bar is exact for its weights (it keeps the
    correlation of positions through the dirty beam's sidelobes, ~1 % here, that eq. 9
    leaves out)."""
    out, _, _ = first
    for n in TYPES:
        for line in _lines(out, n):
            assert line["expected_noise_jy"] == pytest.approx(line["uv_stack_flux_err_jy"],
                                                              rel=0.03)


def test_map_noise_is_the_thermal_noise_where_clean_left_nothing(first):
    """The paper's expected noise (eq. 9, sigma_k measured on the CLEANed residual map) and
    the thermal one (from the visibility weights) are two measurements of the same noise in a
    field whose one bright source CLEAN removed (type 1 here, 6 px per beam): they agree, per
    realisation, to the ~10 % with which the stamps' local rms know sigma_k. On type 2's
    coarser pixels (3 px per beam) CLEAN leaves sidelobes of a bright source that lies between
    pixels (seed 0: 822 components against 78, map noise 1.4x thermal), so the map noise is
    only bounded below there: it holds the thermal noise and what CLEAN left. The summary's
    map noise is the lines' mean."""
    out, _, d = first
    for t in d["types"]:
        lines = _lines(out, t["type"])
        for line in lines:
            ratio = line["image_stack_flux_err_jy"] / line["expected_noise_jy"]
            assert ratio > 0.85, (t["type"], line["seed"], ratio)
            if t["type"] == 1:
                assert ratio < 1.15, (t["type"], line["seed"], ratio)
        assert t["expected_map_noise_jy"] == pytest.approx(
            np.mean([r["image_stack_flux_err_jy"] for r in lines]), rel=1e-12)


def test_subpixel_image_flux_recorded(first):
    """Every line of a non-fit type carries the sub-pixel aligned image stack of the same maps:
    a different number from the nearest-pixel one, within the noise of the truth."""
    out, _, _ = first
    for n in TYPES:
        for line in _lines(out, n):
            sub = line["image_flux_subpixel_jy"]
            assert math.isfinite(sub) and sub != line["image_flux_jy"]
            assert abs(sub - 6e-6) < 5 * line["expected_noise_jy"]


def test_table_one_row_per_type(first):
    out, res, d = first
    table = res.table()
    assert list(table["type"]) == list(TYPES)
    assert str(table["uv_flux_mean_jy"].unit) == "Jy"
    assert table["paper.uv_snr"][0] == 15.8


def test_summary_is_plain_numpy_of_the_jsonl(first):
    out, res, d = first
    for t in d["types"]:
        lines = _lines(out, t["type"])
        assert sorted(r["seed"] for r in lines) == [0, 1]
        uv = np.array([r["uv_flux_jy"] for r in lines])
        im = np.array([r["image_flux_jy"] for r in lines])
        assert t["uv_flux_mean_jy"] == pytest.approx(uv.mean(), rel=1e-12)
        assert t["uv_flux_scatter_jy"] == pytest.approx(uv.std(ddof=1), rel=1e-12)
        assert t["image_flux_mean_jy"] == pytest.approx(im.mean(), rel=1e-12)
        assert t["image_flux_scatter_jy"] == pytest.approx(im.std(ddof=1), rel=1e-12)
        assert t["seconds"] == pytest.approx(sum(r["seconds"] for r in lines), rel=1e-12)
        for r in lines:  # one uv-profile per realisation, on the common bins
            assert len(r["profile"]["re_jy"]) == len(rr.PROFILE_EDGES_KLAMBDA) - 1


def test_paper_rows_are_table_2(first):
    out, res, d = first
    by = {t["type"]: t["paper"] for t in d["types"]}
    for n in TYPES:
        assert by[n] == json.loads(json.dumps(paper.paper_row(n)))
    # Table 2 (tab:simresults), row 1: 6.00±0.47 | 6.02±0.38 (15.8) | 5.89±0.49 (12.0) µJy
    assert by[1]["expected_flux_jy"] == pytest.approx(6.00e-6)
    assert by[1]["expected_noise_jy"] == pytest.approx(0.47e-6)
    assert by[1]["uv_flux_jy"] == pytest.approx(6.02e-6)
    assert by[1]["uv_scatter_jy"] == pytest.approx(0.38e-6)
    assert by[1]["uv_snr"] == 15.8
    # row 2: image-stacking 5.73±0.49 µJy (11.7)
    assert by[2]["image_flux_jy"] == pytest.approx(5.73e-6)
    assert by[2]["image_snr"] == 11.7
    # row 9 (mJy): uv 1.00±0.08 (12.5); row 7's sizes (§4.1.7, Fig. 8): uv 1.50", image 1.55"
    assert paper.PAPER_TABLE2[9]["uv_scatter_jy"] == pytest.approx(0.08e-3)
    assert paper.PAPER_TABLE2[9]["uv_snr"] == 12.5
    sizes = paper.paper_row(7)["sizes"]
    assert sizes["uv_fwhm_arcsec"] == 1.50 and sizes["image_fwhm_arcsec"] == 1.55
    # the procedure choices: 5000 m cut for 5-7 and 11 (§4.1.5, §5: "for uv-stacking in data
    # set 11 we are excluding the shortest baselines"), PSF fit for 7, mosaics for 8-10
    assert {n for n, p in paper.PROCEDURES.items() if p.uvmin_m == 5000.0} == {5, 6, 7, 11}
    assert [n for n, p in paper.PROCEDURES.items() if p.fit_size] == [7]
    assert {n for n, p in paper.PROCEDURES.items() if p.mosaic} == {8, 9, 10}


def test_files_kept_and_temporaries_removed(first):
    out, res, d = first
    for n in TYPES:
        work = out / f"type{n}"
        names = sorted(p.name for p in work.iterdir())
        assert names == ["profile_seed0.npz", rr.JSONL, "stamp_seed0.npz"], names
        with np.load(work / "stamp_seed0.npz") as z:
            assert z["stamp"].ndim == 2 and np.isfinite(z["stamp"]).any()
        with np.load(work / "profile_seed0.npz") as z:
            assert len(z.files) > 1


def test_resume_runs_only_missing_and_redoes_truncated(first, monkeypatch):
    out, res, d = first
    calls = []
    real = rr.run_realization

    def counting(n, seed, *args, **kw):
        calls.append((n, seed))
        return real(n, seed, *args, **kw)

    monkeypatch.setattr(rr, "run_realization", counting)
    before = _lines(out, 1)
    with warnings.catch_warnings():
        # lines made the same way are reused without a word
        warnings.filterwarnings("error", message=".*were made with", category=XstackWarning)
        res3 = rr.reproduce(1, realizations=3, scale=SCALE, outdir=out, procedures=SMALL)
    assert calls == [(1, 2)]
    after = _lines(out, 1)
    assert after[:2] == before and [r["seed"] for r in after] == [0, 1, 2]
    assert res3.types[0].realizations == 3

    # an interrupted write: the last line cut in the middle is ignored and that seed redone
    path = out / "type1" / rr.JSONL
    text = path.read_text()
    last = text.splitlines()[-1]
    path.write_text(text[: len(text) - len(last) // 2 - 1])
    calls.clear()
    res3 = rr.reproduce(1, realizations=3, scale=SCALE, outdir=out, procedures=SMALL)
    assert calls == [(1, 2)]
    assert [r["seed"] for r in _lines(out, 1)] == [0, 1, 2]
    assert res3.types[0].realizations == 3
    # the redone realisation is the same one, to the last bit (CLEAN's components included;
    # imaging is reproducible): only the time it took differs

    def untimed(rec):
        return {k: v for k, v in rec.items() if "seconds" not in k}

    assert untimed(_lines(out, 1)[2]) == untimed(json.loads(last))

    # nothing missing: nothing runs
    calls.clear()
    rr.reproduce(1, realizations=2, scale=SCALE, outdir=out, procedures=SMALL)
    assert calls == []


def test_cli_json_and_table(tmp_path, capsys):
    """The command with the paper's own type-2 procedure (720 x 720 pixels of 0.5")."""
    from xstack.cli import main

    argv = ["reproduce", "--type", "2", "--realizations", "1", "--scale", str(SCALE),
            "--outdir", str(tmp_path), "--no-progress", "-q"]
    assert main([*argv, "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)  # stdout is one JSON object
    (t,) = printed["types"]
    assert KEYS <= set(t) and t["type"] == 2 and t["realizations"] == 1
    (line,) = _lines(tmp_path, 2)
    assert line["procedure"]["size"] == 720 and line["procedure"]["cell_arcsec"] == 0.5
    assert t["uv_flux_mean_jy"] == pytest.approx(line["uv_flux_jy"], rel=1e-12)
    assert t["true_flux_jy"] == pytest.approx(6e-6, rel=1e-12)
    # the human table beside the paper's row; a second run resumes (nothing new to run)
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "uv-stacking" in text and "paper (Table 2)" in text and "(15.8)" in text
    # the paper's expected noise (Table 2's 0.47 µJy) beside xstack's from the residual map
    (map_line,) = [x for x in text.splitlines() if "noise, map (eq. 9)" in x]
    assert map_line.rstrip().endswith("0.470 µJy"), map_line
    assert "noise, map (eq. 9) " in map_line, map_line   # the label stands apart from its value
    assert len(_lines(tmp_path, 2)) == 1
    # --overwrite forgets the earlier realisation and runs it again; without a bar (not a
    # terminal: a batch job's log) each realisation is a line on stderr as it finishes
    assert main([a for a in argv if a != "-q"] + ["--overwrite", "--json"]) == 0
    err = capsys.readouterr().err
    (done,) = [x for x in err.splitlines() if x.startswith("type 2 seed 0: uv ")]
    assert done.endswith("s; 1 of 1 new)") and "µJy" in done, done
    (again,) = _lines(tmp_path, 2)
    assert again["seconds"] != line["seconds"]
    # same seed, same data; multithreaded gridding sums in another order (~1e-6 relative)
    assert again["uv_flux_jy"] == pytest.approx(line["uv_flux_jy"], rel=1e-4)


def test_other_procedure_is_not_resumed(first, monkeypatch):
    out, res, d = first
    calls = []
    monkeypatch.setattr(rr, "run_realization", lambda n, seed, *a, **k: calls.append(seed) or {
        "seed": seed, "seconds": 0.0})
    other = {1: dataclasses.replace(SMALL[1], clean_threshold_jy=30e-6)}
    old = SMALL[1].clean_threshold_jy
    with pytest.warns(XstackWarning, match=rf"type 1: 1 earlier realisation\(s\) in .* \(seeds 0\) "
                      rf"were made with procedure clean_threshold_jy {old} -> 3e-05: they are "
                      r"run again") as got:
        rr.reproduce(1, realizations=1, scale=SCALE, outdir=out, procedures=other)
    assert calls == [0]
    assert [w.message.option for w in got if "were made with" in str(w.message)] == ["outdir"]


def test_made_differently_names_what_changed():
    base = {"scale": 0.1, "procedure": {"size": 64, "epsilon": 1e-4}, "scene_sha256": "a"}
    assert rr.made_differently(base, dict(base)) == ""
    assert rr.made_differently(base, dict(base, scale=1.0)) == "scale 0.1 -> 1.0"
    newer = dict(base, procedure={"size": 64, "epsilon": 1e-6, "image_noise_flat": True})
    assert rr.made_differently(base, newer) == (
        "procedure epsilon 0.0001 -> 1e-06, image_noise_flat unset -> True")
    many = dict(base, procedure={k: 1 for k in "abcdef"})
    assert rr.made_differently(base, many) == (
        "procedure a unset -> 1, b unset -> 1, c unset -> 1 and 5 more")
    assert rr.made_differently(base, dict(base, scene_sha256="b")) == (
        "another scene (the preset has changed)")


def test_changed_scene_is_not_resumed(first, tmp_path, monkeypatch):
    """A record of a preset since changed (here: the presets before they flagged, as the
    records of 2026-12-02 were) is not mixed with the new ones: its seed runs again, and the
    report groups the lines by scene."""

    import xstack
    from xstack.reproduce.report import load_type

    out, res, d = first
    shutil.copytree(out / "type1", tmp_path / "type1")
    old = _lines(tmp_path, 1)
    digest = xstack.preset_scene("paper-1", scale=SCALE).digest()
    assert {r["scene_sha256"] for r in old} == {digest} and len(digest) == 64
    real = xstack.preset_scene

    def unflagged(name, scale=1.0):
        scene = real(name, scale=scale)
        return dataclasses.replace(scene, effects=dataclasses.replace(scene.effects,
                                                                      flagging=None))

    monkeypatch.setattr(xstack, "preset_scene", unflagged)
    assert unflagged("paper-1", SCALE).digest() != digest
    calls = []
    monkeypatch.setattr(rr, "run_realization", lambda n, seed, *a, **k: calls.append(seed) or {
        "seed": seed, "seconds": 0.0})
    with pytest.warns(XstackWarning, match=r"\(seeds 0, 1\) were made with another scene"):
        rr.reproduce(1, realizations=2, scale=SCALE, outdir=tmp_path, procedures=SMALL)
    assert calls == [0, 1]
    used, note = load_type(tmp_path, 1)
    assert [r["seed"] for r in used] == [0, 1] and all(r["seconds"] == 0.0 for r in used)
    assert note.startswith(f"{len(old)} line(s)") and "another scene" in note


def test_dask_client_runs_realizations_as_tasks(first, tmp_path):
    distributed = pytest.importorskip("distributed")
    out, res, d = first
    with distributed.Client(processes=False, n_workers=1, threads_per_worker=1,
                            dashboard_address=None) as client:
        res4 = rr.reproduce(2, realizations=3, scale=SCALE, outdir=out, procedures=SMALL,
                            client=client)
    assert [r["seed"] for r in _lines(out, 2)] == [0, 1, 2]
    assert res4.types[0].realizations == 3
    # the realisation made on the worker is the one this process makes, to the bit
    # (imaging, CLEAN and stacks are reproducible whatever the threads: docs/imaging.md)
    # (seeds 0 and 1 copied, so that the resumed local run makes seed 2 alone)
    (tmp_path / "type2").mkdir()
    lines = (out / "type2" / rr.JSONL).read_text().splitlines()
    (tmp_path / "type2" / rr.JSONL).write_text("\n".join(lines[:2]) + "\n")
    rr.reproduce(2, realizations=3, scale=SCALE, outdir=tmp_path, procedures=SMALL)
    mine, theirs = ({k: v for k, v in _lines(o, 2)[2].items() if k != "seconds"}
                    for o in (tmp_path, out))
    assert mine["seed"] == 2
    assert json.dumps(mine, sort_keys=True) == json.dumps(theirs, sort_keys=True)


def test_clean_threshold_is_the_papers_above_the_noise():
    # §2.2.1: 20 µJy for type 1; §2.2.4: 50 µJy from type 4 on; thermal limit 2.1 µJy (§2.2)
    assert rr.clean_threshold(paper.PROCEDURES[1], 1.0) == 20e-6
    assert rr.clean_threshold(paper.PROCEDURES[7], 1.0) == 50e-6
    assert rr.clean_threshold(paper.PROCEDURES[7], 0.05) == 50e-6
    assert rr.clean_threshold(paper.PROCEDURES[1], 0.01) == pytest.approx(5 * 2.1e-6 / 0.1)


def test_types_refused():
    # all eleven of Table 2, the ALMA mosaics 8-10 included
    assert rr.parse_types("all") == list(range(1, 12))
    assert rr.parse_types(["3", 1]) == [1, 3]
    assert rr.parse_types([9, "8", 10]) == [8, 9, 10]
    for bad in ("12", "x", 0):
        with pytest.raises(OptionError):
            rr.parse_types(bad)
    with pytest.raises(OptionError):
        rr.reproduce(1, realizations=0, outdir="unused")


def test_outdir_that_is_a_file_is_one_line_and_left_alone(tmp_path, capsys):
    """--outdir naming a file (or a type directory that is a file) is refused in one line
    that names the option, before anything runs, and the file is not touched."""
    from xstack.cli import main

    afile = tmp_path / "notadir"
    afile.write_text("keep me")
    with pytest.raises(OptionError, match="is not a directory"):
        rr.reproduce(1, realizations=1, scale=0.01, outdir=afile)
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "type1").write_text("keep me too")
    with pytest.raises(OptionError, match="type1 exists and is not a directory"):
        rr.reproduce(1, realizations=1, scale=0.01, outdir=tmp_path / "out")
    assert main(["reproduce", "--type", "1", "--realizations", "1", "--scale", "0.01",
                 "--outdir", str(afile), "-q"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "--outdir" in err[0], err
    assert afile.read_text() == "keep me"
    assert (tmp_path / "out" / "type1").read_text() == "keep me too"


def test_type7_fits_sizes(tmp_path):
    """Type 7's chain adds the Gaussian fits (uv beyond 5000 m, image with the PSF): sizes
    and fitted fluxes per realisation, their mean and scatter in ``sizes``. A coarse image
    (1.5" pixels over a 35' image) keeps it quick; the numbers are not the paper's here."""
    proc = {7: dataclasses.replace(paper.PROCEDURES[7], cell_arcsec=1.5, size=1400)}
    res = rr.reproduce(7, realizations=2, scale=SCALE, outdir=tmp_path, procedures=proc)
    (t,) = res.to_dict()["types"]
    assert t["paper"]["sizes"] == paper.PAPER_TYPE7_SIZES
    lines = _lines(tmp_path, 7)
    s = t["sizes"]
    for domain in ("uv", "image"):
        failed = 0
        for r in lines:
            # a fit that fails on a noisy realisation is recorded as missing, with its reason
            assert r[f"{domain}_flux_jy"] == r[f"{domain}_fit_flux_jy"]
            if r[f"{domain}_fwhm_arcsec"] is None:
                failed += 1
                assert r[f"{domain}_fit_error"]
        assert s[f"{domain}_fits_failed"] == failed
        fw = [r[f"{domain}_fwhm_arcsec"] for r in lines if r[f"{domain}_fwhm_arcsec"] is not None]
        if fw:
            assert s[f"{domain}_fwhm_mean_arcsec"] == pytest.approx(np.mean(fw), rel=1e-12)
    for r in lines:
        assert r["true_flux_jy"] == pytest.approx(2.96e-6, rel=1e-12)  # Table 1 / §2.2.7
        assert math.isfinite(r["image_flux_filtered_jy"])
    # Fig. 12: the first realisation keeps the filtered stamp; the filter zeroes the Fourier
    # cells below 5000 m, the zero-spacing one among them, so the stamp sums to zero
    with np.load(tmp_path / "type7" / "stamp_seed0.npz") as z:
        stamp, filtered = z["stamp"], z["stamp_filtered"]
    assert filtered.shape == stamp.shape
    assert abs(filtered.sum()) < 1e-9 * np.abs(filtered).sum()
    assert not np.allclose(filtered, stamp)
    # the recorded filtered flux is the filtered stamp's center divided by the filter
    # response, the share of a point source's peak the filter keeps (well below 1 at 5000 m)
    first = next(r for r in lines if r["seed"] == 0)
    c = filtered.shape[0] // 2
    assert 0.3 < first["image_filter_response"] < 0.95
    assert first["image_flux_filtered_jy"] == pytest.approx(
        filtered[c, c] / first["image_filter_response"], rel=1e-9)


def test_records_of_types_1_2_have_no_figure_extras(first):
    """The Fig. 1 subsets and the Fig. 12 filtered flux belong to types 5-7 only."""
    out, res, d = first
    for n in TYPES:
        for r in _lines(out, n):
            assert "uv_flux_subsets_jy" not in r and "image_flux_filtered_jy" not in r
            # the single-pointing procedure is recorded as before (resumes earlier runs)
            assert "pointing_size" not in r["procedure"]


def test_subset_sizes():
    assert rr.subset_sizes(45) == [10, 30, 45]
    assert rr.subset_sizes(900) == [10, 30, 100, 300, 900]
    assert rr.subset_sizes(1000) == [10, 30, 100, 300, 1000]
    assert rr.subset_sizes(300) == [10, 30, 100, 300]
    assert rr.subset_sizes(7) == [7]


def test_type5_subsets_and_filtered_flux(tmp_path, monkeypatch):
    """Type 5 records carry the uv-stacked flux of the first N targets (Fig. 1) and the
    image-stacked flux with the 5000 m uv-plane filter (Fig. 12). 45 targets (a tiny scale
    with the target count of scale 0.05) give the subsets 10, 30 and 45; the stacks of the
    subsets are checked to be made on the first N rows of the target catalog, the same
    residual data each time."""
    import xstack

    _counts(monkeypatch, targets=45)
    seen = []
    real = xstack.stack_uv

    def recording(data, positions, **kw):
        seen.append((str(data), list(np.asarray(positions["ra"], dtype=float))))
        # weights that lie, as on a field whose CLEAN left much: every stack would say so
        warnings.warn(WeightsWarning("uv-stack flux error from WEIGHT (1e-07 Jy) and from the "
                                     "visibility scatter (2e-07 Jy) differ by 2x",
                                     option="errors"), stacklevel=2)
        return real(data, positions, **kw)

    monkeypatch.setattr(xstack, "stack_uv", recording)
    proc = {5: dataclasses.replace(paper.PROCEDURES[5], cell_arcsec=1.5, size=1400)}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = rr.reproduce(5, realizations=1, scale=SCALE, outdir=tmp_path, procedures=proc)
    # said once, by the all-targets stack; not again by the subsets of the same data
    said = [w for w in caught if issubclass(w.category, WeightsWarning)]
    assert len(said) == 1 and len(seen) == 3
    (line,) = _lines(tmp_path, 5)
    subsets = line["uv_flux_subsets_jy"]
    assert list(subsets) == ["10", "30", "45"] and line["n_targets"] == 45
    assert all(math.isfinite(v) for v in subsets.values())
    # all targets: the flux of the record, and of the summary
    assert subsets["45"] == pytest.approx(line["uv_flux_jy"], rel=1e-12, abs=0)
    assert res.types[0].uv_flux_mean_jy == pytest.approx(subsets["45"], rel=1e-12)
    # nested: every stack is of the first N positions of the all-targets stack, same data
    full = max(seen, key=lambda x: len(x[1]))
    assert sorted(len(ra) for _, ra in seen) == [10, 30, 45]
    for data, ra in seen:
        assert data == full[0] and ra == full[1][: len(ra)]
    assert math.isfinite(line["image_flux_filtered_jy"])
    assert line["image_flux_filtered_jy"] != line["image_flux_jy"]


def _counts(monkeypatch, mosaic_arcsec=None, **counts):
    """The presets with these population counts (e.g. ``bright=3``) at any scale and, with
    ``mosaic_arcsec``, a contiguous mosaic of that side instead of 100"."""
    import xstack

    real = xstack.preset_scene

    def scene(name, scale=1.0):
        s = real(name, scale=scale)
        for p in s.populations:
            p.count = counts.get(p.name, p.count)
            if mosaic_arcsec is not None and p.positions.kind == "box":
                p.positions.size_arcsec = [mosaic_arcsec, mosaic_arcsec]
        if mosaic_arcsec is not None:
            s.pointings.size_arcsec = [mosaic_arcsec, mosaic_arcsec]
        return s

    monkeypatch.setattr(xstack, "preset_scene", scene)


def test_mosaic_type9_per_pointing(tmp_path, monkeypatch):
    """Type 9 (non-contiguous ALMA mosaic): each pointing CLEANed on its own, its model
    subtracted from its own visibilities, all pointings uv-stacked together and the pointing
    images image-stacked. Three pointings, one integration (scale 0.01), 0.4" pixels."""
    _counts(monkeypatch, bright=3)  # type 9 has one pointing on each bright source
    proc = {9: dataclasses.replace(paper.PROCEDURES[9], cell_arcsec=0.4, size=128)}
    res = rr.reproduce(9, realizations=1, scale=0.01, outdir=tmp_path, procedures=proc)
    (t,) = json.loads(json.dumps(res.to_dict()))["types"]
    assert KEYS <= set(t) and t["type"] == 9 and t["realizations"] == 1
    # Table 1 / §2.3.2: targets of 1 mJy; Table 2 row 9 (mJy): 1.00 ± 0.09 | 1.00 ± 0.08
    # (12.5) | 0.97 ± 0.09 (10.8)
    assert t["true_flux_jy"] == pytest.approx(1e-3, rel=1e-12)
    assert t["paper"]["expected_noise_jy"] == pytest.approx(0.09e-3)
    assert t["paper"]["uv_scatter_jy"] == pytest.approx(0.08e-3)
    assert t["paper"]["image_flux_jy"] == pytest.approx(0.97e-3)
    assert t["paper"]["image_snr"] == 10.8
    (line,) = _lines(tmp_path, 9)
    assert line["pointings"] == 3 and line["clean_components"] > 0
    # the ALMA weights sigma_k = 1/A (§3.2): "pb" in both stacks
    assert line["procedure"]["uv_weighting"] == line["procedure"]["image_weighting"] == "pb"
    for k in ("uv_flux_jy", "image_flux_jy", "expected_noise_jy", "uv_stack_flux_err_jy"):
        assert math.isfinite(line[k]), k
    # a detection-level stack of 10 targets: within 5 expected sigma of 1 mJy
    for k in ("uv_flux_jy", "image_flux_jy"):
        assert abs(line[k] - 1e-3) < 5 * line["expected_noise_jy"], (k, line[k])
    names = sorted(p.name for p in (tmp_path / "type9").iterdir())
    assert names == ["profile_seed0.npz", rr.JSONL, "stamp_seed0.npz"], names


@pytest.mark.slow  # ~15 s on a loaded machine: type 9 covers the per-pointing chain by default
def test_mosaic_type8_joint(tmp_path, monkeypatch):
    """Type 8 (contiguous ALMA mosaic): CLEANed pointing by pointing, image-stacked on the
    joint linear mosaic. A 40" mosaic (a few 20"-spaced pointings), one integration."""
    _counts(monkeypatch, mosaic_arcsec=40.0)
    proc = {8: dataclasses.replace(paper.PROCEDURES[8], cell_arcsec=0.4, size=160,
                                   pointing_size=128)}
    res = rr.reproduce(8, realizations=1, scale=0.01, outdir=tmp_path, procedures=proc)
    (t,) = json.loads(json.dumps(res.to_dict()))["types"]
    # Table 1 / §2.3.1: targets of 1 mJy; Table 2 row 8 (mJy): 0.98 ± 0.12 (8.2) | 0.90 ± 0.11
    assert t["true_flux_jy"] == pytest.approx(1e-3, rel=1e-12)
    assert t["paper"]["uv_flux_jy"] == pytest.approx(0.98e-3)
    assert t["paper"]["image_flux_jy"] == pytest.approx(0.90e-3)
    (line,) = _lines(tmp_path, 8)
    assert line["pointings"] > 1 and line["procedure"]["pointing_size"] == 128
    for k in ("uv_flux_jy", "image_flux_jy", "expected_noise_jy"):
        assert math.isfinite(line[k]), k
    for k in ("uv_flux_jy", "image_flux_jy"):
        assert abs(line[k] - 1e-3) < 5 * line["expected_noise_jy"], (k, line[k])


def test_work_directory_of_a_killed_run_is_named(first, tmp_path):
    """A realisation's work directory left by a run killed outright (SIGKILL: no clean-up)
    gets one warning naming it and its size when the next run starts; the run neither
    removes it (it could be another run's, going on now) nor runs differently."""
    out, res, d = first
    shutil.copytree(out / "type1", tmp_path / "type1")
    stale = tmp_path / "type1" / "seed7-abc123"
    (stale / "sim.zarr").mkdir(parents=True)
    (stale / "sim.zarr" / "chunk").write_bytes(b"\0" * 3_000_000)
    with pytest.warns(XstackWarning, match=r"1 work directory .*seed7-abc123; 0\.003 GB") as w:
        again = rr.reproduce(1, realizations=2, scale=SCALE, outdir=tmp_path, procedures=SMALL)
    assert [x.message.option for x in w if isinstance(x.message, XstackWarning)] == ["outdir"]
    assert stale.is_dir()
    assert again.types[0].uv_flux_mean_jy == res.types[0].uv_flux_mean_jy

    # none left: no warning
    shutil.rmtree(stale)
    with warnings.catch_warnings():
        warnings.simplefilter("error", XstackWarning)
        rr.reproduce(1, realizations=2, scale=SCALE, outdir=tmp_path, procedures=SMALL)
