"""MSs written by ``xstack export`` are what CASA needs (issue 11 item 2).

CASA 6.7's listobs segfaulted or aborted (``std::bad_alloc``) in some runs on exported MSs:
its ``MSMetaData`` indexes the STATE -> intent table with the main table's STATE_ID without a
bounds check once STATE has a row, and export wrote STATE_ID = -1 beside a STATE row.

* Fast tests (python-casacore only): the exported MS obeys the rules found by comparing it
  with MSs that CASA writes itself (``casatools.simulator``) and with the real MSs of the
  pyuvdata wheel; the truth is casacore's own MS definition (``required_ms_desc``,
  ``complete_ms_desc``) and those rules, not xstack's writer.
* Slow tests (``-m slow``, the ``casa`` extra): CASA itself runs listobs and tclean on
  exported MSs, five times each, every call in its own process (a crash fails the test, not
  the run), and the tclean image is compared pixel by pixel with that of the MS the store came
  from (a converted real MS, an MS simulated by CASA) or with the known sky (a store simulated
  by xstack: a point source of known flux on a known pixel).
"""

from __future__ import annotations

import importlib.util
import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import casacore.tables as pt
import numpy as np
import pytest

import xstack
from xstack.testing import make_test_ms, require_real_ms

#: Subtables CASA opens for listobs and tclean, each with its required columns.
SUBTABLES = ("ANTENNA", "DATA_DESCRIPTION", "FEED", "FIELD", "FLAG_CMD", "HISTORY", "OBSERVATION",
             "POINTING", "POLARIZATION", "PROCESSOR", "SPECTRAL_WINDOW", "STATE", "SOURCE")

#: Columns whose cells may stay undefined (CASA writes them so itself).
MAY_BE_UNDEFINED = {("MAIN", "FLAG_CATEGORY"), ("SOURCE", "POSITION")}

#: Runs of each CASA task per exported MS (crashes showed in 1-3 of 5 runs).
REPEATS = 5


# --------------------------------------------------------------------------------------
# structure (fast, no CASA)
# --------------------------------------------------------------------------------------

def casa_problems(ms: Path) -> list[str]:
    """What in ``ms`` breaks the rules CASA relies on; empty if nothing.

    Rules: the subtables exist with casacore's required columns and value types; every id of
    the main table is a row of its subtable; STATE_IDs are STATE rows (or all -1 with STATE
    empty); SOURCE has REST_FREQUENCY, SYSVEL and TRANSITION with NUM_LINES elements per cell
    and the measure keywords of the MS definition; no array cell is undefined.
    """
    ms = str(ms)
    problems: list[str] = []
    with pt.table(ms, ack=False) as main:
        keywords = main.getkeywords()
        tables = {"MAIN": main}
        nrows: dict[str, int] = {}
        for name in SUBTABLES:
            if name not in keywords or not os.path.isdir(os.path.join(ms, name)):
                problems.append(f"{name}: subtable missing")
                continue
            with pt.table(os.path.join(ms, name), ack=False) as sub:
                nrows[name] = sub.nrows()
                required = pt.required_ms_desc(name)
                for col, cd in required.items():
                    if col.startswith("_"):
                        continue
                    if col not in sub.colnames():
                        problems.append(f"{name}.{col}: required column missing")
                    elif sub.getcoldesc(col)["valueType"] != cd["valueType"]:
                        problems.append(f"{name}.{col}: value type {sub.getcoldesc(col)['valueType']}"
                                        f" instead of {cd['valueType']}")
                problems += _undefined_cells(name, sub)
        problems += _undefined_cells("MAIN", tables["MAIN"])
        if len(nrows) < len(SUBTABLES):
            return problems

        def col(name: str) -> np.ndarray:
            return main.getcol(name)

        state = col("STATE_ID")
        if nrows["STATE"] > 0:
            if state.min() < 0 or state.max() >= nrows["STATE"]:
                problems.append(f"STATE_ID in [{state.min()}, {state.max()}] beside {nrows['STATE']} "
                                "STATE row(s): CASA's MSMetaData reads past its intent table")
        elif np.any(state != -1):
            problems.append("STATE_ID >= 0 but STATE is empty")
        for column, sub in (("FIELD_ID", "FIELD"), ("DATA_DESC_ID", "DATA_DESCRIPTION"),
                            ("ANTENNA1", "ANTENNA"), ("ANTENNA2", "ANTENNA"),
                            ("OBSERVATION_ID", "OBSERVATION")):
            ids = col(column)
            if ids.min() < 0 or ids.max() >= nrows[sub]:
                problems.append(f"{column} in [{ids.min()}, {ids.max()}], {sub} has {nrows[sub]} rows")
        proc = col("PROCESSOR_ID")
        if proc.max() >= max(nrows["PROCESSOR"], 1) or proc.min() < -1:
            problems.append(f"PROCESSOR_ID in [{proc.min()}, {proc.max()}], PROCESSOR has "
                            f"{nrows['PROCESSOR']} rows")
        with pt.table(os.path.join(ms, "FEED"), ack=False) as feed:
            feeds = set(zip(feed.getcol("ANTENNA_ID").tolist(), feed.getcol("FEED_ID").tolist()))
        for a, f in (("ANTENNA1", "FEED1"), ("ANTENNA2", "FEED2")):
            used = set(zip(col(a).tolist(), col(f).tolist()))
            if not used <= feeds:
                problems.append(f"({a}, {f}) {sorted(used - feeds)[:3]} not in FEED")
        with pt.table(os.path.join(ms, "DATA_DESCRIPTION"), ack=False) as dd:
            if dd.getcol("SPECTRAL_WINDOW_ID").max() >= nrows["SPECTRAL_WINDOW"]:
                problems.append("DATA_DESCRIPTION.SPECTRAL_WINDOW_ID beyond SPECTRAL_WINDOW")
            if dd.getcol("POLARIZATION_ID").max() >= nrows["POLARIZATION"]:
                problems.append("DATA_DESCRIPTION.POLARIZATION_ID beyond POLARIZATION")

    with pt.table(os.path.join(ms, "SOURCE"), ack=False) as src:
        full = pt.complete_ms_desc("SOURCE")
        for name in ("REST_FREQUENCY", "SYSVEL", "TRANSITION"):
            if name not in src.colnames():
                problems.append(f"SOURCE.{name}: column missing (CASA writes it)")
                continue
            want = full[name].get("keywords", {}).get("MEASINFO", {}).get("type")
            got = src.getcolkeywords(name).get("MEASINFO", {}).get("type")
            if want != got:
                problems.append(f"SOURCE.{name}: measure type {got!r} instead of {want!r}")
            for r in range(src.nrows()):
                n = len(src.getcell(name, r))
                if n != src.getcell("NUM_LINES", r):
                    problems.append(f"SOURCE.{name} row {r}: {n} values, NUM_LINES "
                                    f"{src.getcell('NUM_LINES', r)}")
        source_ids = set(src.getcol("SOURCE_ID").tolist())
    with pt.table(os.path.join(ms, "FIELD"), ack=False) as field:
        missing = set(field.getcol("SOURCE_ID").tolist()) - source_ids - {-1}
        if missing:
            problems.append(f"FIELD.SOURCE_ID {sorted(missing)} not in SOURCE")
    return problems


def _undefined_cells(name: str, tab) -> list[str]:
    out = []
    n = tab.nrows()
    for col in tab.colnames():
        if (name, col) in MAY_BE_UNDEFINED or n == 0:
            continue
        rows = range(n) if n <= 2000 else np.linspace(0, n - 1, 2000).astype(int)
        bad = [int(r) for r in rows if not tab.iscelldefined(col, int(r))]
        if bad:
            out.append(f"{name}.{col}: undefined cells (rows {bad[:5]})")
    return out


def _roundtrip(ms: Path, tmp: Path) -> Path:
    store = xstack.convert_ms(ms, tmp / (ms.stem + ".zarr"))
    return xstack.export_ms(store, tmp / (ms.stem + ".export.ms"))


def test_exported_generated_ms_is_what_casa_needs(tmp_path):
    ms = make_test_ms(tmp_path / "gen.ms", n_antennas=5, n_times=6, n_channels=3, n_fields=2,
                      n_spws=2, missing_baselines=1, seed=3)
    # the generated MS itself (all STATE_IDs -1): STATE must then be empty
    assert casa_problems(ms) == []
    with pt.table(str(ms / "STATE"), ack=False) as st:
        assert st.nrows() == 0
    out = _roundtrip(ms, tmp_path)
    assert casa_problems(out) == []
    with pt.table(str(out), ack=False) as t, pt.table(str(out / "STATE"), ack=False) as st:
        assert set(t.getcol("STATE_ID").tolist()) == {0}
        assert st.nrows() == 1 and st.getcell("OBS_MODE", 0) == "OBSERVE_TARGET#ON_SOURCE"


@pytest.mark.realdata
@pytest.mark.parametrize("name", ["evla", "alma"])
def test_exported_real_ms_is_what_casa_needs(tmp_path, name):
    ms = require_real_ms(name, tmp_path)
    out = _roundtrip(ms, tmp_path)
    assert casa_problems(out) == []


def test_write_subtables_states_follow_the_main_table(tmp_path):
    """STATE gets a row for every STATE_ID in use (none when all are -1)."""
    from xstack.io._mswrite import create_ms, write_subtables

    ms = tmp_path / "s.ms"
    tab = create_ms(ms, [(2, 2)])
    tab.addrows(4)
    tab.putcol("STATE_ID", np.array([0, 2, 1, 2], dtype=np.int32))
    tab.close()
    write_subtables(ms, antenna_names=["A", "B"], antenna_positions=np.zeros((2, 3)),
                    dish_diameters=np.full(2, 12.0), telescope_name="ALMA",
                    fields=[{"name": "f", "phase_center": (1.0, -0.5)}],
                    spws=[{"chan_freq": np.array([1e9, 1.1e9]), "chan_width": np.full(2, 1e8)}],
                    pol_setups=[["XX", "YY"]], data_descriptions=[(0, 0)], time_range=(0.0, 1.0))
    with pt.table(str(ms / "STATE"), ack=False) as st:
        assert st.nrows() == 3


# --------------------------------------------------------------------------------------
# CASA itself (slow; the 'casa' extra)
# --------------------------------------------------------------------------------------

class Casa:
    """An offline CASA 6 set-up in a temporary directory: site config, private HOME."""

    def __init__(self, root: Path):
        import casadata  # a path only; importing it starts nothing

        self.work = root / "work"
        home = root / "home"
        self.work.mkdir()
        home.mkdir()
        site = root / "casasiteconfig.py"
        data = str(casadata.datapath)
        site.write_text(textwrap.dedent(f"""\
            measurespath = {data!r}
            datapath = [{data!r}]
            measures_auto_update = False
            data_auto_update = False
            nogui = True
            """))
        self.env = dict(os.environ, HOME=str(home), CASASITECONFIG=str(site), MPLBACKEND="Agg",
                        OMP_NUM_THREADS="1")

    def run(self, code: str, *args: object, timeout: float = 600) -> str:
        """Run ``code`` (with ``sys.argv[1:] = args``) in a new python process; fail on a crash."""
        proc = subprocess.run([sys.executable, "-c", code, *map(str, args)], cwd=self.work,
                              env=self.env, capture_output=True, text=True, timeout=timeout)
        if proc.returncode != 0:
            rc = proc.returncode
            how = f"killed by {signal.Signals(-rc).name}" if rc < 0 else f"exit status {rc}"
            tail = "\n".join((proc.stdout + proc.stderr).strip().splitlines()[-15:])
            pytest.fail(f"CASA {how} on {args}:\n{tail}")
        return proc.stdout


LISTOBS = textwrap.dedent("""\
    import sys
    from casatasks import listobs
    vis, listfile = sys.argv[1:3]
    summary = listobs(vis=vis, listfile=listfile, overwrite=True)
    assert summary, "listobs returned nothing"
    print("listobs ok")
    """)

TCLEAN = textwrap.dedent("""\
    import json, sys
    import numpy as np
    from casatasks import tclean
    from casatools import image
    vis, out, opts = sys.argv[1], sys.argv[2], json.loads(sys.argv[3])
    tclean(vis=vis, imagename=out, specmode="mfs", gridder="standard", weighting="natural",
           niter=0, stokes="I", datacolumn="data", **opts)
    ia = image()
    ia.open(out + ".image")
    np.save(out + ".npy", ia.getchunk()[:, :, 0, 0])
    ia.close()
    print("tclean ok")
    """)

CASA_SIMULATE = textwrap.dedent("""\
    import sys
    import numpy as np
    from casatools import componentlist, measures, simulator
    out = sys.argv[1]
    sm, me, cl = simulator(), measures(), componentlist()
    cl.addcomponent(dir="J2000 10h00m02s -29d59m30s", flux=2.0, fluxunit="Jy", freq="100GHz",
                    shape="point")
    cl.rename(out + ".cl")
    cl.close()
    sm.open(out)
    rng = np.random.default_rng(1)
    x, y = rng.uniform(-300, 300, 8), rng.uniform(-300, 300, 8)
    sm.setconfig(telescopename="ALMA", x=x.tolist(), y=y.tolist(), z=[0.0] * 8,
                 dishdiameter=[12.0] * 8, mount=["alt-az"], antname=[f"A{i}" for i in range(8)],
                 coordsystem="local", referencelocation=me.observatory("ALMA"))
    sm.setspwindow(spwname="B3", freq="100GHz", deltafreq="50MHz", freqresolution="50MHz",
                   nchannels=4, stokes="XX YY")
    sm.setfeed(mode="perfect X Y")
    sm.setfield(sourcename="src", sourcedirection=me.direction("J2000", "10h00m00s", "-30d00m00s"))
    sm.setlimits(shadowlimit=0.001, elevationlimit="8.0deg")
    sm.setauto(autocorrwt=0.0)
    sm.settimes(integrationtime="30s", usehourangle=True, referencetime=me.epoch("utc", "2024/01/01"))
    sm.observe("src", "B3", starttime="-1800s", stoptime="1800s")
    sm.setvp(dovp=False)
    sm.predict(complist=out + ".cl")
    sm.close()
    print("simulated")
    """)


@pytest.fixture(scope="module")
def casa(tmp_path_factory) -> Casa:
    for module in ("casatools", "casatasks", "casadata"):
        if importlib.util.find_spec(module) is None:
            pytest.skip(f"{module} is not installed (pip install -e '.[test,casa]')")
    return Casa(tmp_path_factory.mktemp("casa"))


def _xstack_simulated(tmp: Path, cell_arcsec: float, dx: int, dy: int, flux: float):
    """A store simulated by xstack: one point source of ``flux`` Jy on pixel (c + dx, c + dy)
    of a CASA image (RA increases to the left, so x = c - l/cell, y = c + m/cell)."""
    ra0, dec0 = np.deg2rad(150.0), np.deg2rad(30.0)
    cell = np.deg2rad(cell_arcsec / 3600)
    l, m = -dx * cell, dy * cell
    n = np.sqrt(1 - l * l - m * m)  # SIN projection, inverted (Calabretta & Greisen 2002)
    dec = np.arcsin(m * np.cos(dec0) + n * np.sin(dec0))
    ra = ra0 + np.arctan2(l, n * np.cos(dec0) - m * np.sin(dec0))
    scene = {
        "name": "casa-check",
        "array": {"config": "vla.d"},
        "observation": {"date": "2014-01-01", "hour_angle": [-1.0, 1.0], "integration": 60.0,
                        "time_per_pointing": 1200.0},
        "spectral": {"center": 1.4e9, "bandwidth": 16e6, "channels": 4, "polarizations": ["RR", "LL"]},
        "pointings": {"mode": "single", "center": [150.0, 30.0]},
        "effects": {"primary_beam": "none", "w_term": True},
        "populations": [{"name": "src", "count": 1, "flux": {"kind": "fixed", "value": f"{flux}Jy"},
                         "positions": {"kind": "list", "ra": [float(np.rad2deg(ra))],
                                       "dec": [float(np.rad2deg(dec))]}}],
    }
    store = tmp / "xsim.zarr"
    xstack.simulate(scene, store)
    return store


def _check_with_casa(casa: Casa, exported: Path, source: Path | None, tclean_opts: dict,
                     n_rows: int) -> list[np.ndarray]:
    """listobs and tclean REPEATS times on ``exported`` (each call a process); return the images,
    after checking them against the image of ``source`` (if given) pixel by pixel."""
    opts = json.dumps(tclean_opts)
    for k in range(REPEATS):
        listfile = casa.work / f"{exported.name}.{k}.listobs.txt"
        casa.run(LISTOBS, exported, listfile)
        assert f"Data records: {n_rows} " in listfile.read_text()
    images = []
    for k in range(REPEATS):
        out = casa.work / f"{exported.name}.img{k}"
        casa.run(TCLEAN, exported, out, opts)
        images.append(np.load(str(out) + ".npy"))
    if source is not None:
        out = casa.work / f"{source.name}.img"
        casa.run(TCLEAN, source, out, opts)
        want = np.load(str(out) + ".npy")
        peak = np.abs(want).max()
        assert peak > 0
        for img in images:
            np.testing.assert_allclose(img, want, rtol=0, atol=1e-5 * peak)
    return images


def _nrows(ms: Path) -> int:
    with pt.table(str(ms), ack=False) as t:
        return t.nrows()


@pytest.mark.slow
@pytest.mark.casa
@pytest.mark.timeout(1800)
def test_casa_reads_and_images_export_of_xstack_simulation(casa, tmp_path):
    """A store simulated by xstack, exported: CASA images the source where and as bright as
    it was put (1.5 Jy on a known pixel; the dirty image of one point source at its own pixel
    is its flux, whatever the uv coverage)."""
    size, cell, dx, dy, flux = 128, 4.0, 12, 7, 1.5
    store = _xstack_simulated(tmp_path, cell, dx, dy, flux)
    ms = xstack.export_ms(store, tmp_path / "xsim.ms")
    assert casa_problems(ms) == []
    images = _check_with_casa(casa, ms, None, {"imsize": [size, size], "cell": f"{cell}arcsec"},
                              _nrows(ms))
    c = size // 2
    for img in images:
        assert np.unravel_index(np.argmax(img), img.shape) == (c + dx, c + dy)
        assert img[c + dx, c + dy] == pytest.approx(flux, rel=1e-4)
        np.testing.assert_array_equal(img, images[0])


@pytest.mark.slow
@pytest.mark.casa
@pytest.mark.timeout(1800)
def test_casa_reads_and_images_export_of_casa_simulation(casa, tmp_path):
    """An MS that CASA simulated (2 Jy point source), converted and exported: same image."""
    src = tmp_path / "casa_sim.ms"
    casa.run(CASA_SIMULATE, src)
    out = _roundtrip(src, tmp_path)
    assert casa_problems(out) == []
    images = _check_with_casa(casa, out, src, {"imsize": [256, 256], "cell": "0.3arcsec"}, _nrows(src))
    # the 2 Jy source is on the image (off a pixel center, so a little fainter)
    assert 1.6 < np.max(images[0]) < 2.002


@pytest.mark.slow
@pytest.mark.casa
@pytest.mark.realdata
@pytest.mark.timeout(1800)
@pytest.mark.parametrize("name, opts", [
    ("evla", {"imsize": [128, 128], "cell": "2arcsec"}),
    # three fields in FIELD, data in field 2 only
    ("alma", {"imsize": [128, 128], "cell": "0.5arcsec", "field": "2"}),
])
def test_casa_reads_and_images_export_of_real_ms(casa, tmp_path, name, opts):
    src = require_real_ms(name, tmp_path)
    out = _roundtrip(src, tmp_path)
    _check_with_casa(casa, out, src, opts, _nrows(src))
