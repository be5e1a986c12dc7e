"""A Stokes-I-only store is measured like any other (issue 10, item 9).

It used to image but fail to uv-stack ("no selected polarization among ['I']"): the stages
each had their own list of parallel hands. Truth: equation 4 and the weighted mean written
out in plain numpy here.
"""

from __future__ import annotations

import numpy as np
import pytest
from astropy.table import Table
from conftest import make_partition

import xstack
from xstack.coords import SPEED_OF_LIGHT, radec_to_lmn
from xstack.fit._data import as_partitions, stokes_i_blocks


def _numpy_stack(ds, ra, dec):
    ra0, dec0 = ds.attrs["phase_center"]
    l, m, _, n1 = radec_to_lmn(np.radians(ra), np.radians(dec), ra0, dec0)
    uvw = ds["UVW"].values.reshape(-1, 3)
    f = ds["frequency"].values
    phase = 2 * np.pi * (uvw[:, 0:1] * l + uvw[:, 1:2] * m + uvw[:, 2:3] * n1) * f / SPEED_OF_LIGHT
    vis = ds["VISIBILITY"].values.reshape(uvw.shape[0], f.size, -1)
    w = np.where(ds["FLAG"].values, 0.0, ds["WEIGHT"].values.astype(np.float64)).reshape(vis.shape)
    rot = vis * np.exp(-1j * phase)[..., None]
    return float(np.sum(w * rot.real) / np.sum(w))


def test_uvstack_of_a_stokes_i_store():
    ds = make_partition(pols=("I",), seed=3, dtype=np.complex128)
    ra0, dec0 = np.degrees(ds.attrs["phase_center"])
    ra, dec = ra0 + 2e-4, dec0 - 1e-4
    # smearing="none": the plain equation 4 at channel centers, as the numpy truth
    res = xstack.stack_uv(xstack_tree(ds), Table({"ra": [ra], "dec": [dec]}), weighting="none",
                         primary_beam="none", smearing="none")
    assert res.flux_jy == pytest.approx(_numpy_stack(ds, ra, dec), rel=1e-9, abs=1e-12)
    assert res.n_visibilities == int((~ds["FLAG"].values).sum())


def test_i_and_parallel_hands_are_the_same_vocabulary_everywhere():
    from xstack._select import PARALLEL_HANDS
    from xstack.imaging import image, subtract
    from xstack.uvstack import stack

    for mod in (image, subtract, stack):
        assert getattr(mod, "PARALLEL_HANDS", PARALLEL_HANDS) is PARALLEL_HANDS
    ds = make_partition(pols=("I",), seed=4)
    (name, part), = as_partitions(ds)
    (_, vis, wt), *_ = list(stokes_i_blocks(part, name))
    assert vis.shape[-1] == 1 and wt.shape[-1] == 1


def xstack_tree(ds):
    import xarray as xr

    return xr.DataTree.from_dict({"/": xr.Dataset(), "/part": ds})
