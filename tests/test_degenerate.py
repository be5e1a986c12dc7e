"""Degenerate uv coverage is said, not passed on silently (issue 11 item 7).

One baseline in one integration puts every visibility on one line through the uv origin:
the PSF is a set of stripes and a Gaussian "beam" fitted to it (2493673.86" x 2.72" in the
issue) means nothing. The truth here is geometric and independent of the imager: the uv
points are built by hand on a line (or at the origin), or spread in 2-D.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from astropy.io import fits

from xstack.errors import XstackError
from xstack.imaging.image import UVDIM_KEY, make_image
from xstack.schema import new_partition

PC = (math.radians(150.0), math.radians(2.0))


def _partition(uvw: np.ndarray, a1, a2, n_chan: int = 4) -> object:
    """A partition of a 1 Jy point source at the phase center on the given (time, bl, 3) uvw."""
    nt, nb = uvw.shape[:2]
    n_ant = int(max(max(a1), max(a2))) + 1
    shape = (nt, nb, n_chan, 2)
    return new_partition(
        visibility=np.ones(shape, np.complex64), weight=np.ones(shape, np.float32),
        flag=np.zeros(shape, bool), uvw=uvw, time=5e9 + 10.0 * np.arange(nt),
        antenna1=np.asarray(a1), antenna2=np.asarray(a2),
        antenna_names=[f"A{i}" for i in range(n_ant)],
        antenna_positions=np.zeros((n_ant, 3)) + np.arange(n_ant)[:, None],
        dish_diameters=np.full(n_ant, 25.0), frequency=1.4e9 + 1e6 * np.arange(n_chan),
        channel_width=np.full(n_chan, 1e6), polarization=["XX", "YY"], phase_center=PC,
        telescope_name="VLA", integration_time=10.0)


def _image(ds, size=64, cell=1.0):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = make_image(ds, size=size, cell_arcsec=cell)
    msgs = [str(w.message) for w in caught if issubclass(w.category, UserWarning)]
    return res, msgs


def test_one_baseline_one_integration_is_one_dimensional():
    uvw = np.array([[[3000.0, 1000.0, 5.0]]])  # (1 time, 1 baseline, 3)
    res, msgs = _image(_partition(uvw, [0], [1]))
    assert len(msgs) == 1 and "one-dimensional" in msgs[0] and "1 baseline" in msgs[0]
    assert res.header[UVDIM_KEY] == 1
    # the line's position angle: atan2(u, v) = atan2(3000, 1000) = 71.6 deg east of north
    assert f"{math.degrees(math.atan2(3000, 1000)):.1f} deg" in msgs[0]


def test_collinear_baselines_in_a_snapshot_are_one_dimensional():
    # an east-west line of 6 antennas, one integration: all baselines parallel
    x = np.array([0.0, 35.0, 90.0, 400.0, 1100.0, 2500.0])
    a1, a2 = np.triu_indices(x.size, 1)
    b = (x[a2] - x[a1])[None, :]
    uvw = np.stack([b * 0.8, b * -0.6, b * 0.01], axis=-1)  # one direction in the uv plane
    res, msgs = _image(_partition(uvw, a1, a2))
    assert len(msgs) == 1 and "one-dimensional" in msgs[0] and "15 baselines" in msgs[0]
    assert res.header[UVDIM_KEY] == 1


def test_zero_area_coverage_is_an_error():
    uvw = np.zeros((3, 1, 3))
    with pytest.raises(XstackError, match="zero extent"):
        make_image(_partition(uvw, [0], [1]), size=64, cell_arcsec=1.0)


def test_single_channel_and_integration_of_a_2d_array_is_fine():
    rng = np.random.default_rng(3)
    n_ant = 10
    xy = rng.uniform(-1500, 1500, size=(n_ant, 2))
    a1, a2 = np.triu_indices(n_ant, 1)
    d = xy[a2] - xy[a1]
    uvw = np.concatenate([d, np.zeros((d.shape[0], 1))], axis=1)[None]
    res, msgs = _image(_partition(uvw, a1, a2, n_chan=1), size=128, cell=1.0)
    assert msgs == []
    assert res.header[UVDIM_KEY] == 2
    assert res.beam[0] < 128 * 1.0  # a real, bounded beam


def test_nearly_one_dimensional_beam_longer_than_the_image(tmp_path):
    # one baseline over 4 minutes of earth rotation: a short arc, the beam far longer than
    # a small image (the ALMA test MS in the pyuvdata wheel is such a case)
    h = np.radians(np.linspace(0, 1.0, 24))
    uvw = np.stack([2000 * np.cos(h), 2000 * np.sin(h), 0 * h], axis=-1)[:, None, :]
    res, msgs = _image(_partition(uvw, [0], [1]), size=64, cell=2.0)
    assert len(msgs) == 1 and "longer than the image" in msgs[0]
    assert res.header[UVDIM_KEY] == 1
    # and the image written says so to anyone who reads its header
    path = res.write(tmp_path / "img.fits")
    assert fits.getheader(path)[UVDIM_KEY] == 1


def test_cli_prints_one_warning_line(tmp_path, capsys):
    from xstack.cli import main
    from xstack.schema import write_store

    uvw = np.array([[[3000.0, 1000.0, 5.0]]])
    store = write_store({"spw0_field0": _partition(uvw, [0], [1])}, tmp_path / "one.zarr")
    status = main(["image", str(store), str(tmp_path / "one.fits"), "--size", "64",
                   "--cell", "1", "--no-progress"])
    err = capsys.readouterr().err
    assert status == 0
    lines = [ln for ln in err.splitlines() if ln.startswith("warning:")]
    assert len(lines) == 1 and "uv coverage is one-dimensional" in lines[0]
