"""Imaging on the real EVLA and ALMA MeasurementSets shipped with pyuvdata 3.2.3.

The data are uncalibrated, so no clean point source is expected; what must hold is the
adjointness of imaging and prediction on the real uv geometry, and a WCS that puts each
partition's phase center at the reference pixel.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

pytestmark = pytest.mark.realdata


@pytest.fixture(scope="module", params=["evla", "alma"])
def real_store(request, tmp_path_factory):
    testing = pytest.importorskip("xstack.testing")
    convert = pytest.importorskip("xstack.io.convert")
    d = tmp_path_factory.mktemp(request.param)
    ms = testing.require_real_ms(request.param, d)
    return request.param, convert.convert_ms(ms, d / "data.zarr")


def test_real_adjoint_and_wcs(real_store):
    from xstack.imaging.image import _parallel_hands, grid_visibilities, make_image, predict
    from xstack.schema import iter_partitions, open_store

    name, path = real_store
    rng = np.random.default_rng(11)
    for pname, ds in iter_partitions(open_store(path)):
        uvw = ds.UVW.values
        freq = ds.frequency.values
        flag = ds.FLAG.values
        if np.all(flag[..., _parallel_hands(ds, pname)]):
            continue
        good = np.all(np.isfinite(uvw), axis=-1)
        uvw_rows = uvw[good]
        # a cell that samples the longest baseline at the highest frequency
        umax = np.max(np.hypot(uvw_rows[:, 0], uvw_rows[:, 1])) * freq.max() / 299792458.0
        cell_arcsec = 0.25 / max(umax, 1.0) * 180 / math.pi * 3600
        n = 64
        x = rng.normal(size=(n, n))
        shape = (uvw_rows.shape[0], freq.size)
        y = rng.normal(size=shape) + 1j * rng.normal(size=shape)
        lhs = np.sum(grid_visibilities(uvw_rows, freq, y, np.ones(y.shape), n, n,
                                       cell_arcsec * math.pi / 180 / 3600, epsilon=1e-10) * x)
        rhs = np.real(np.vdot(predict(x, cell_arcsec, uvw_rows, freq, epsilon=1e-10), y))
        assert abs(lhs - rhs) < 1e-6 * abs(lhs), (name, pname)
        res = make_image(path, size=n, cell_arcsec=cell_arcsec, partitions=pname)
        assert np.all(np.isfinite(res.image))
        assert res.psf[n // 2, n // 2] == pytest.approx(1.0, abs=1e-5)
        ra0, dec0 = ds.attrs["phase_center"]
        ra, dec = res.wcs.pixel_to_world_values(n // 2, n // 2)
        assert ra == pytest.approx(math.degrees(ra0) % 360, abs=1e-9)
        assert dec == pytest.approx(math.degrees(dec0), abs=1e-9)
