"""``docs/tutorial.md`` runs as written and its numbers match the injected truth.

The ```bash blocks of the tutorial are extracted and run in order, each as one ``bash``
script, in a temporary directory with the ``xstack`` console script of this install first on
PATH; the ```toml block is saved as ``survey.toml`` (the page tells the reader to). Every
block must exit with status 0. The ```text block after a bash block lists lines the block
prints: each must appear in its output, in order (numbers compared to their printed
precision, ``...`` matches anything), so neither the commands nor the quoted output can
drift from the code. The key numbers are then checked against the truth of the scene file
itself (60 targets of 20 uJy, sigma = 10 mJy per visibility part, the VLA A array): the
stacked fluxes within 5 sigma of 20 uJy, the image rms and the stack's error bar against
the radiometer prediction, the visibility and row counts, the phase center of the stack at
the targets' mean position.

The block after ``<!-- needs the casa extra -->`` (CASA's listobs and tclean on the export)
runs only in the slow, ``casa``-marked test, and only when casatools, casatasks and casadata
are installed; it runs with a private HOME so no ``~/.casa`` of the machine is read or written.
"""

from __future__ import annotations

import importlib.util
import math
import os
import re
import subprocess
import sys
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

TUTORIAL = Path(__file__).resolve().parents[1] / "docs" / "tutorial.md"
CASA_MARK = "<!-- needs the casa extra -->"

#: What the scene file in the tutorial must say (the truth the checks below rely on).
N_ANTENNAS_VLA = 27


@dataclass
class Block:
    """One ```bash block of the tutorial and the ```text block quoting its output."""

    script: str
    expected: list[str] = field(default_factory=list)
    casa: bool = False
    stdout: str = ""
    stderr: str = ""


def parse_tutorial(text: str) -> tuple[str, list[Block]]:
    """The scene (the ```toml block) and the bash blocks, in order."""
    fences = list(re.finditer(r"^```(\w*)\n(.*?)^```\s*$", text, flags=re.M | re.S))
    tomls = [m.group(2) for m in fences if m.group(1) == "toml"]
    assert len(tomls) == 1, "the tutorial has one scene file"
    blocks: list[Block] = []
    for m in fences:
        lang, body = m.group(1), m.group(2)
        if lang == "bash":
            before = text[:m.start()].rstrip().splitlines()
            blocks.append(Block(script=body, casa=bool(before) and before[-1].strip() == CASA_MARK))
        elif lang == "text" and blocks:
            blocks[-1].expected += [line for line in body.splitlines() if line.strip()]
    return tomls[0], blocks


NUMBER = r"[-+−]?\d[\d,]*(?:\.\d+)?(?:[eE][-+]?\d+)?"


def _value(token: str) -> float:
    return float(token.replace(",", "").replace("−", "-"))


def _line_pattern(expected: str) -> tuple[re.Pattern, list[str]]:
    """A regex for one quoted output line (numbers captured, ``...`` a wildcard)."""
    parts, numbers = [], []
    for k, chunk in enumerate(expected.strip().split("...")):
        if k:
            parts.append(".*?")
        pos = 0
        for m in re.finditer(NUMBER, chunk):
            parts.append(r"\s+".join(map(re.escape, re.split(r" +", chunk[pos:m.start()]))))
            parts.append(f"({NUMBER})")
            numbers.append(m.group(0))
            pos = m.end()
        parts.append(r"\s+".join(map(re.escape, re.split(r" +", chunk[pos:]))))
    return re.compile("".join(parts)), numbers


def _close(quoted: str, got: str) -> bool:
    """``got`` equals the ``quoted`` number to the quoted precision (2 % for measurements)."""
    a, b = _value(quoted), _value(got)
    decimals = len(quoted.split(".")[1]) if "." in quoted and "e" not in quoted.lower() else 0
    if "." not in quoted and "e" not in quoted.lower():
        return a == b  # counts, sizes, dates: exact
    return abs(a - b) <= max(0.02 * abs(a), 1.5 * 10.0 ** -decimals)


def missing_lines(expected: list[str], output: str) -> list[str]:
    """The quoted lines not found, in order, in ``output``."""
    lines = [line.strip() for line in output.splitlines()]
    missing, start = [], 0
    for want in expected:
        pattern, numbers = _line_pattern(want)
        for i in range(start, len(lines)):
            m = pattern.fullmatch(lines[i])
            if m and all(_close(q, g) for q, g in zip(numbers, m.groups(), strict=True)):
                start = i + 1
                break
        else:
            missing.append(want)
    return missing


P = r"(?P<p>[mµun]?)Jy"  # a flux unit with its SI prefix (one per line)


def _jy(text: str, pattern: str) -> tuple[float, ...]:
    """The numbers captured by ``pattern`` (which ends with the unit ``P``) in Jy."""
    m = re.search(pattern, text)
    assert m, f"{pattern!r} not in:\n{text}"
    scale = {"": 1.0, "m": 1e-3, "µ": 1e-6, "u": 1e-6, "n": 1e-9}[m.group("p")]
    skip = m.re.groupindex["p"]
    return tuple(_value(g) * scale for k, g in enumerate(m.groups(), start=1) if k != skip)


def _parse_flux_value(value: str) -> float:
    m = re.fullmatch(r"([\d.eE+-]+)\s*(m|u|µ)?Jy", value)
    assert m, value
    return float(m.group(1)) * {None: 1.0, "m": 1e-3, "u": 1e-6, "µ": 1e-6}[m.group(2)]


def _env() -> dict[str, str]:
    """This install's ``xstack`` first on PATH; no terminal, so no progress bars."""
    bindir = Path(sys.executable).parent
    assert (bindir / "xstack").exists(), f"no xstack console script beside {sys.executable}"
    env = dict(os.environ, PATH=f"{bindir}{os.pathsep}{os.environ.get('PATH', '')}",
               MPLBACKEND="Agg")
    env.pop("CASASITECONFIG", None)
    return env


def run_block(block: Block, cwd: Path, env: dict[str, str], timeout: float = 600) -> None:
    proc = subprocess.run(["bash", "-euo", "pipefail", "-c", block.script], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=timeout)
    block.stdout, block.stderr = proc.stdout, proc.stderr
    assert proc.returncode == 0, (f"exit status {proc.returncode} of\n{block.script}\n"
                                  f"stdout:\n{proc.stdout[-3000:]}\nstderr:\n{proc.stderr[-3000:]}")
    missing = missing_lines(block.expected, proc.stdout + "\n" + proc.stderr)
    assert not missing, ("docs/tutorial.md quotes output lines the command does not print "
                         f"(update the page):\n{block.script}\nmissing:\n" + "\n".join(missing)
                         + f"\nstdout:\n{proc.stdout}\nstderr:\n{proc.stderr[-3000:]}")


@dataclass
class Run:
    workdir: Path
    scene: dict
    blocks: list[Block]

    def output(self, command: str) -> str:
        """stdout of the (first) block that runs ``command``."""
        for b in self.blocks:
            if not b.casa and re.search(rf"^{re.escape(command)}\b", b.script, flags=re.M):
                return b.stdout
        raise AssertionError(f"no block runs {command!r}")


@pytest.fixture(scope="module")
def tutorial(tmp_path_factory) -> Run:
    """Run every non-CASA block of the tutorial once, in order."""
    text = TUTORIAL.read_text(encoding="utf-8")
    scene_text, blocks = parse_tutorial(text)
    assert "`survey.toml`" in text
    work = tmp_path_factory.mktemp("tutorial")
    (work / "survey.toml").write_text(scene_text, encoding="utf-8")
    env = _env()
    for block in blocks:
        if not block.casa:
            run_block(block, work, env)
    return Run(work, tomllib.loads(scene_text), blocks)


# --------------------------------------------------------------------------------------
# the page itself (fast)
# --------------------------------------------------------------------------------------

def test_tutorial_covers_the_whole_workflow():
    text = TUTORIAL.read_text(encoding="utf-8")
    _, blocks = parse_tutorial(text)
    commands = [re.findall(r"^xstack (\w+)", b.script, flags=re.M) for b in blocks]
    flat = [c for cs in commands for c in cs]
    order = ["simulate", "info", "image", "subtract", "uvstack", "fit", "noise", "imstack",
             "export"]
    positions = [flat.index(c) for c in order]
    assert positions == sorted(positions), flat
    assert blocks[-1].casa and "listobs" in blocks[-1].script and "tclean" in blocks[-1].script
    assert all(b.expected for b in blocks), "every command block quotes its key output"
    # linked from the README's documentation table and from the generated docs/cli.md
    root = TUTORIAL.parents[1]
    assert "(docs/tutorial.md)" in (root / "README.md").read_text(encoding="utf-8")
    assert "(tutorial.md)" in (root / "docs" / "cli.md").read_text(encoding="utf-8")


def test_quoted_lines_match_to_printed_precision():
    quoted = ["stacked flux 21.67 ± 3.18 µJy (from WEIGHT; ...) from 60 positions, 168,480 vis"]
    assert not missing_lines(quoted, "stacked flux 21.68 ± 3.18 µJy (from WEIGHT; x) from 60 "
                             "positions, 168,480 vis")
    assert missing_lines(quoted, "stacked flux 25.00 ± 3.18 µJy (from WEIGHT; x) from 60 "
                         "positions, 168,480 vis")
    assert missing_lines(quoted, "stacked flux 21.67 ± 3.18 µJy (from WEIGHT; x) from 61 "
                         "positions, 168,480 vis")
    assert missing_lines(["a 1", "b 2"], "b 2\na 1")  # order matters


# --------------------------------------------------------------------------------------
# the workflow (about a minute) against the truth of the scene
# --------------------------------------------------------------------------------------

def test_tutorial_runs_and_recovers_the_injected_flux(tutorial):
    scene, work = tutorial.scene, tutorial.workdir
    targets = {p["name"]: p for p in scene["populations"]}["targets"]
    truth = _parse_flux_value(targets["flux"]["value"])
    n_targets = targets["count"]
    assert scene["array"]["config"] == "vla.a" and scene["pointings"]["mode"] == "single"
    sigma = scene["effects"]["noise"]["sigma"]
    obs, spec = scene["observation"], scene["spectral"]
    n_times = int(obs["time_per_pointing"] // obs["integration"])
    n_baselines = N_ANTENNAS_VLA * (N_ANTENNAS_VLA - 1) // 2
    n_vis = n_times * n_baselines * spec["channels"] * len(spec["polarizations"])
    image_rms = sigma / math.sqrt(n_vis)        # natural weighting, every visibility alike
    stack_err = image_rms / math.sqrt(n_targets)  # before the (small) primary-beam correction

    out = tutorial.output("xstack simulate")
    assert f"{n_vis:,} visibilities" in out and f"({n_targets} sources)" in out
    out = tutorial.output("xstack info")
    assert f"{n_baselines} cross-correlations" in out and f"{n_vis} visibilities" in out
    assert f"{n_times} time stamps" in out and "0.0% flagged" in out

    out = tutorial.output("xstack image survey.zarr")
    (peak,) = _jy(out, rf"peak ({NUMBER}) {P}/beam")
    (rms,) = _jy(out, rf"residual rms ({NUMBER}) {P}/beam")
    bright = _parse_flux_value({p["name"]: p for p in scene["populations"]}["bright"]["flux"]["value"])
    assert 0.8 * bright < peak <= 1.01 * bright
    assert rms == pytest.approx(image_rms, rel=0.1)

    out = tutorial.output("xstack uvstack")
    flux, err = _jy(out, rf"stacked flux ({NUMBER}) ± ({NUMBER}) {P}")
    (err_emp,) = _jy(out, rf"visibility scatter: ± ({NUMBER}) {P}")
    assert f"from {n_targets} positions" in out
    assert abs(flux - truth) < 5 * err and flux / err > 4
    assert err == pytest.approx(stack_err, rel=0.1)
    assert err_emp == pytest.approx(err, rel=0.2)

    out = tutorial.output("xstack fit stacked.zarr")
    fit_flux, fit_err = _jy(out, rf"flux += ({NUMBER}) ± ({NUMBER}) {P}")
    assert abs(fit_flux - truth) < 5 * fit_err
    assert "unresolved" in out  # the targets are point sources

    out = tutorial.output("xstack noise")
    (noise,) = _jy(out, rf"noise += ({NUMBER}) {P}")
    (bias,) = _jy(out, rf"bias += ({NUMBER}) {P}")
    assert noise == pytest.approx(err, rel=0.5)
    assert abs(bias) < 3 * noise / math.sqrt(20)

    out = tutorial.output("xstack image residual.zarr")  # this block also runs imstack and fit
    (rms,) = _jy(out, rf"residual rms ({NUMBER}) {P}/beam")
    assert rms == pytest.approx(image_rms, rel=0.1)
    im_flux, im_err = _jy(out, rf"stacked flux ({NUMBER}) ± ({NUMBER}) {P}/beam")
    assert abs(im_flux - truth) < 5 * im_err and im_flux / im_err > 4
    imfit, imfit_err = _jy(out, rf"flux += ({NUMBER}) ± ({NUMBER}) {P}")
    assert abs(imfit - truth) < 5 * imfit_err

    out = tutorial.output("xstack export")
    assert f"{n_times * n_baselines:,} rows" in out
    from astropy.table import Table

    cat = Table.read(work / "survey.targets.ecsv")
    assert len(cat) == n_targets and np.allclose(np.asarray(cat["flux"]), truth)
    m = re.search(rf"\(({NUMBER}), ({NUMBER}) deg\) \({n_times * n_baselines} rows\)", out)
    assert m, out
    ra, dec = np.deg2rad(np.asarray(cat["ra"])), np.deg2rad(np.asarray(cat["dec"]))
    mean = np.array([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)]).mean(axis=1)
    mean_ra = np.rad2deg(np.arctan2(mean[1], mean[0])) % 360
    mean_dec = np.rad2deg(np.arctan2(mean[2], np.hypot(mean[0], mean[1])))
    assert abs(_value(m.group(1)) - mean_ra) * np.cos(np.deg2rad(mean_dec)) * 3600 < 0.01
    assert abs(_value(m.group(2)) - mean_dec) * 3600 < 0.01

    for name in ("survey.png", "stacked_uvprofile.png", "fit_uv.png", "noise_mc.png",
                 "imstack.png", "stacked.ms"):
        assert (work / name).exists(), name


@pytest.mark.slow
@pytest.mark.casa
@pytest.mark.timeout(1200)
def test_tutorial_casa_step(tutorial):
    """CASA reads the export, and the center of its dirty image is the stacked flux."""
    for module in ("casatools", "casatasks", "casadata"):
        if importlib.util.find_spec(module) is None:
            pytest.skip(f"{module} is not installed (pip install -e '.[test,casa]')")
    casa_blocks = [b for b in tutorial.blocks if b.casa]
    assert len(casa_blocks) == 1
    home = tutorial.workdir / "home"
    home.mkdir(exist_ok=True)
    env = dict(_env(), HOME=str(home))
    run_block(casa_blocks[0], tutorial.workdir, env)
    out = casa_blocks[0].stdout
    m = re.search(rf"center pixel: ({NUMBER}) uJy/beam", out)
    assert m, out
    casa_flux = _value(m.group(1)) * 1e-6
    uv_flux, uv_err = _jy(tutorial.output("xstack uvstack"),
                          rf"stacked flux ({NUMBER}) ± ({NUMBER}) {P}")
    assert casa_flux == pytest.approx(uv_flux, abs=0.02 * uv_err)
    assert "Data records: 21060" in out
