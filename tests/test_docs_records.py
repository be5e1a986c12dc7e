"""The reproduction page's full-size tables are those of the realisation lines in the repository.

``docs/records/flagged/type<N>/realizations.jsonl`` are the lines ``xstack reproduce`` wrote
for the page's "with the simulator's flags" sections. Checked here, with plain numpy on the
lines (not the report writer): the page's row of each type says what the lines say, and the
lines were simulated from today's presets (their scene digest), so a change of a preset that
makes the page stale fails here rather than going unnoticed.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from _bench_helpers import load_benchmark

import xstack

DOCS = Path(__file__).resolve().parents[1] / "docs"
RECORDS = DOCS / "records" / "flagged"
TYPES = sorted(int(p.name[4:]) for p in RECORDS.glob("type*") if (p / "realizations.jsonl").exists())


def _lines(n: int, records: Path = RECORDS) -> list[dict]:
    text = (records / f"type{n}" / "realizations.jsonl").read_text(encoding="utf-8")
    return [json.loads(x) for x in text.splitlines()]


def _row(section: str, n: int) -> list[str] | None:
    """The cells of type ``n``'s first row in the first of the page's sections whose title
    starts with ``section`` that has one; None if none has."""
    page = (DOCS / "reproduction.md").read_text(encoding="utf-8")
    for sec in page.split("\n## "):
        if not sec.startswith(section):
            continue
        # a row starts with the type; "| 10 | " inside a line is another type's R or value
        line = next((x for x in sec.splitlines() if x.startswith(f"| {n} | ")), None)
        if line is not None:
            return [c.strip() for c in line.strip("|").split("|")]
    return None


def _section_row(n: int) -> list[str]:
    """The row of type ``n`` in the first table of the page's flagged section holding it."""
    row = _row("Full size with the simulator's flags", n)
    if row is None:
        raise AssertionError(f"no flagged section of docs/reproduction.md has a row of type {n}")
    return row


def test_records_exist():
    assert TYPES, "docs/records/flagged holds no realisation lines"


@pytest.mark.parametrize("n", TYPES)
def test_records_are_of_todays_presets(n):
    lines = _lines(n)
    seeds = [r["seed"] for r in lines]
    assert len(set(seeds)) == len(seeds), "a seed twice"
    scales = {r["scale"] for r in lines}
    assert len(scales) == 1
    (scale,) = scales
    digest = xstack.preset_scene(f"paper-{n}", scale=scale).digest()
    assert {r.get("scene_sha256") for r in lines} == {digest}, (
        f"type {n}: the preset has changed since docs/records was made; run the type again")


@pytest.mark.parametrize("n", TYPES)
def test_page_row_is_the_records(n):
    lines = _lines(n)
    row = _section_row(n)
    per_jy = {"µJy": 1e6, "mJy": 1e3}[row[3]]  # the ALMA types 8-10 are in mJy
    uv = np.array([r["uv_flux_jy"] for r in lines]) * per_jy
    im = np.array([r["image_flux_jy"] for r in lines]) * per_jy
    true = np.mean([r["true_flux_jy"] for r in lines]) * per_jy
    noise = np.mean([r["expected_noise_jy"] for r in lines]) * per_jy
    assert row[1] == str(len(lines))
    assert row[4] == f"{true:.2f} ± {noise:.2f}"
    assert row[5] == f"{uv.mean():.2f} ± {uv.std(ddof=1):.2f} ({uv.mean() / uv.std(ddof=1):.1f})"
    assert row[6] == f"{im.mean():.2f} ± {im.std(ddof=1):.2f} ({im.mean() / im.std(ddof=1):.1f})"
    offset = (uv.mean() - true) / (uv.std(ddof=1) / np.sqrt(len(uv)))
    assert row[10] == f"{offset:+.1f}"


@pytest.mark.parametrize("n", TYPES)
def test_expected_noise_table_is_the_records(n):
    """Thermal and map (eq. 9) expected noise and the scatters, as the lines say; every type
    with lines is in the table."""
    row = _row("Expected noise: the paper's", n)
    assert row is not None, f"type {n} has lines but no row in the expected-noise table"
    lines = _lines(n)
    per_jy = {"µJy": 1e6, "mJy": 1e3}[row[2]]
    col = lambda k: np.array([r[k] for r in lines], dtype=float) * per_jy  # noqa: E731
    thermal, mapn = col("expected_noise_jy").mean(), col("image_stack_flux_err_jy").mean()
    uv, im = col("uv_flux_jy").std(ddof=1), col("image_flux_jy").std(ddof=1)
    assert row[1] == str(len(lines))
    assert row[3:5] == [f"{thermal:.3f}", f"{mapn:.3f}"]
    assert row[6:8] == [f"{uv:.3f}", f"{im:.3f}"]
    if row[8] != "n/a":  # type 7's fluxes are fits
        assert row[8:10] == [f"{uv / mapn:.2f}", f"{uv / thermal:.2f}"]


@pytest.mark.parametrize("n", TYPES)
def test_summary_ratios_are_the_records(n):
    """The summary's ratios of each type, from the lines with plain numpy and Table 2."""
    from xstack.reproduce.paper import PAPER_TABLE2

    row = _row("Summary: the full-size runs", n)
    assert row is not None, f"type {n} has lines but no row in the summary"
    lines = _lines(n)
    paper = PAPER_TABLE2[n]
    uv = np.array([r["uv_flux_jy"] for r in lines])
    im = np.array([r["image_flux_jy"] for r in lines])
    true = np.mean([r["true_flux_jy"] for r in lines])
    offset = (uv.mean() - true) / (uv.std(ddof=1) / np.sqrt(len(uv)))
    snr = lambda a: a.mean() / a.std(ddof=1)  # noqa: E731
    assert row[1] == str(len(lines))
    assert row[2] == f"{offset:+.1f}"
    assert row[3] == f"{uv.std(ddof=1) / paper['uv_scatter_jy']:.2f}"
    assert row[4] == f"{im.mean() / uv.mean():.3f}"
    assert row[5] == f"{paper['image_flux_jy'] / paper['uv_flux_jy']:.3f}"
    if "image_flux_subpixel_jy" in lines[0]:
        sub = np.array([r["image_flux_subpixel_jy"] for r in lines])
        assert row[6] == f"{sub.mean() / uv.mean():.3f}"
    assert row[7] == f"{snr(uv) / snr(im):.2f}"
    assert row[8] == f"{paper['uv_snr'] / paper['image_snr']:.2f}"


CHECKS = DOCS / "records" / "sigma-check"
CHECK_TYPES = sorted(int(p.name[4:]) for p in CHECKS.glob("type*")
                     if (p / "realizations.jsonl").exists())


@pytest.mark.parametrize("n", CHECK_TYPES)
def test_paired_sigma_check_is_the_records(n):
    """The paired check of today's image σ_k: its row, from the new lines and the same seeds
    of the published ones, with plain numpy; the new lines record the clipped estimator, the
    old ones not, and both are the same observation (scene digest, seeds)."""
    new = _lines(n, CHECKS)
    published = {r["seed"]: r for r in _lines(n)}
    old = [published[r["seed"]] for r in new]
    assert {r["scene_sha256"] for r in new} == {r["scene_sha256"] for r in old}
    assert all(r["procedure"]["image_noise_estimator"] == "clipped" for r in new)
    assert all("image_noise_estimator" not in r["procedure"] for r in old)
    row = _row("Types 3 and 4 with today's", n)
    assert row is not None, f"type {n} has check lines but no row in the paired check"
    col = lambda rs, k: np.array([r[k] for r in rs], dtype=float)  # noqa: E731
    seeds = [r["seed"] for r in new]
    assert seeds == list(range(len(seeds)))
    assert row[1] == f"0–{len(seeds) - 1}"
    change = col(new, "image_flux_jy") / col(old, "image_flux_jy") - 1
    assert row[2] == (f"{100 * change.mean():+.2f} ± "
                      f"{100 * change.std(ddof=1) / np.sqrt(len(change)):.2f}")
    uv_change = col(new, "uv_flux_jy") / col(old, "uv_flux_jy") - 1
    assert row[3] == f"{100 * np.abs(uv_change).max():.2f}"

    def ratio(rs, k):
        return f"{col(rs, k).mean() / col(rs, 'uv_flux_jy').mean():.4f}"

    assert row[4] == f"{ratio(old, 'image_flux_jy')} → {ratio(new, 'image_flux_jy')}"
    assert row[5] == (f"{ratio(old, 'image_flux_subpixel_jy')} → "
                      f"{ratio(new, 'image_flux_subpixel_jy')}")
    sd = lambda a: f"{1e9 * a.std(ddof=1):.1f}"  # noqa: E731
    assert row[6] == f"{sd(col(old, 'image_flux_jy'))} → {sd(col(new, 'image_flux_jy'))}"
    diff = lambda rs: col(rs, "image_flux_jy") - col(rs, "uv_flux_jy")  # noqa: E731
    assert row[7] == f"{sd(diff(old))} → {sd(diff(new))}"
    assert row[8] == f"{col(new, 'seconds').mean():.0f}"


SKY = DOCS / "records" / "sky-effects"
SKY_SECTION = "What the image stack's deficit is made of"


def _sky(n: int, variant: str) -> list[dict]:
    return sorted((json.loads(p.read_text(encoding="utf-8"))
                   for p in (SKY / f"type{n}" / variant).glob("seed*.json")),
                  key=lambda r: r["seed"])


def test_sky_effects_tables_are_the_records():
    """The ingredient runs' tables, from their lines and the published lines of the same
    seeds, with plain numpy; the lines are of today's benchmark scenes (digest)."""
    bench = load_benchmark("diagnose_sky_effects")
    tn = _sky(6, "targets+noise")
    assert tn and {r["scene_sha256"] for r in tn} == {
        bench.variant_scene(6, 1.0, "targets+noise").digest()}
    full = {r["seed"]: r for r in _lines(6)}
    keys = ("uv_flux_jy", "image_flux_jy", "image_flux_subpixel_jy")
    for r in tn:
        row = _row(SKY_SECTION, r["seed"])
        assert row is not None, f"seed {r['seed']} has a line but no row"
        want = [f"{1e6 * r[k]:.3f}" for k in keys] + [f"{1e6 * full[r['seed']][k]:.3f}" for k in keys]
        assert row[1:] == want
    page = (DOCS / "reproduction.md").read_text(encoding="utf-8")
    # the section's text with its lines joined (a number may wrap onto the next line)
    sec = " ".join(page.split(f"## {SKY_SECTION}")[1].split("\n## ")[0].split())
    col = lambda rs, k: 1e6 * np.array([x[k] for x in rs])  # noqa: E731
    fl = [full[r["seed"]] for r in tn]
    for rs, k in ((tn, "image_flux_jy"), (tn, "image_flux_subpixel_jy"), (fl, "image_flux_jy"),
                  (fl, "image_flux_subpixel_jy")):
        d = col(rs, k) - col(rs, "uv_flux_jy")
        text = f"{d.mean():+.3f} ± {d.std(ddof=1) / np.sqrt(d.size):.3f}".replace("-", "−")
        assert text.lstrip("+") in sec, text
    (t7,), (t7b,) = _sky(7, "targets"), _sky(7, "targets+bright")
    for r, v in ((t7, "targets"), (t7b, "targets+bright")):
        assert r["scene_sha256"] == bench.variant_scene(7, 1.0, v).digest()
    for label, dom in (("uv (Gaussian beyond 5000 m)", "uv"), ("image (PSF-convolved Gaussian)", "image")):
        cells = [f"{1e6 * r[f'{dom}_flux_jy']:.3f} | {r[f'{dom}_fwhm_arcsec']:.3f}" for r in (t7, t7b)]
        assert f"| {label} | {cells[0]} | {cells[1]} |" in sec
    conf = json.loads((SKY / "type6" / "confusion-targets+bright-seed0.json").read_text())
    assert (f"−{-1e6 * conf['target_minus_true_mean_jy']:.3f} ± "
            f"{1e6 * conf['target_minus_true_se_jy']:.3f} µJy") in sec
    assert f"+{1e6 * conf['random_positions']['mean_jy']:.3f} µJy" in sec


CASA_SECTION = "CASA's CLEAN in place of xstack's: type 6 without noise (2026-12-07)"
CASA_ROWS = {"x6_int60": "xstack, Clark", "c6_int60_clark": "CASA tclean, Clark",
             "c6_int60_hogbom": "CASA tclean, Högbom",
             "c6_int60_ms": "CASA tclean, multiscale (0, 3″, 10″)",
             "x6_int60_s1": "xstack, Clark", "c6_int60_clark_s1": "CASA tclean, Clark"}


def test_casa_clean_table_is_the_records():
    """The CASA-against-xstack CLEAN table, row by row from its records (µJy, mJy), and the
    records are of one scene: today's noiseless type-6 variant with 60 s integrations."""
    bench = load_benchmark("diagnose_sky_effects")
    digest = bench.variant_scene(6, 1.0, "targets+bright", integration=60.0).digest()
    assert len(list((SKY / "type6" / "casa").glob("*.json"))) == len(CASA_ROWS)
    page = (DOCS / "reproduction.md").read_text(encoding="utf-8")
    sec = page.split(f"## {CASA_SECTION}")[1].split("\n## ")[0]
    for stem, label in CASA_ROWS.items():
        r = json.loads((SKY / "type6" / "casa" / f"{stem}.json").read_text(encoding="utf-8"))
        assert r["scene_sha256"] == digest and r["integration_s"] == 60.0
        assert r["clean"].startswith("CASA" if stem.startswith("c6") else "xstack")
        st = r["stacks_jy"]
        img, uv_all, uv_cut = (1e6 * st[k] for k in (
            "image sub-pixel, sigma2", "uv all baselines, sigma2", "uv > 5000 m, sigma2"))
        assert r["seed"] == (1 if stem.endswith("_s1") else 0)
        cells = [str(r["seed"]), label, str(r["clean_iterations"]), f"{1e3 * r['model_total_jy']:.2f}",
                 f"{1e6 * r['bright_left_mean_jy']['all baselines']:.1f}",
                 f"{1e6 * r['target_minus_true_mean_jy']:+.3f}".replace("-", "−"),
                 f"{img:.3f}", f"{uv_all:.3f}", f"{uv_cut:.3f}", f"{img / uv_cut:.3f}"]
        assert "| " + " | ".join(cells) + " |" in sec, label
