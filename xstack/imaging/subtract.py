"""Model subtraction: the residual store both stacking methods use (the paper's residual MS).

``subtract(data, model, out)`` with ``model`` either

* a **component catalog** (anything :func:`xstack.coords.read_catalog` reads) with ``ra``,
  ``dec``, ``flux`` (Jy, integrated) and optional ``fwhm_arcsec`` (circular Gaussian FWHM):
  predicted exactly with the paper's equation 1 (float64 phases, w-term, Gaussian factor),
  each source attenuated by the telescope's standard primary beam
  (:func:`xstack.beams.standard_beam`) at its distance from the partition's phase center
  (taken as the pointing center), per channel; or
* a **CLEAN model image** (FITS, Jy/pixel, SIN grid centered on the data's phase center, as
  ``xstack image`` writes ``OUT.model.fits``): predicted with ducc0 ``dirty2vis``. It is an
  apparent-flux model (made from the un-corrected image), so no primary beam is applied.

The model (Stokes I, unpolarised) is subtracted from the parallel hands (XX, YY / RR, LL);
cross-hands are copied unchanged. Output is written lazily, chunk by chunk.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr

from xstack._select import PARALLEL_HANDS, autocorrelation_mask
from xstack.errors import XstackError

_ARCSEC = math.pi / (180.0 * 3600.0)


def _model_kind(model: Any) -> str:
    from astropy.io import fits
    from astropy.table import Table

    if isinstance(model, Table):
        return "catalog"
    path = Path(model)
    if not path.exists():
        raise XstackError(f"{path}: no such model file")
    if path.suffix.lower() in (".fits", ".fit", ".fts", ".fz"):
        try:
            with fits.open(path) as hdul:
                for hdu in hdul:
                    if hdu.is_image and hdu.data is not None and hdu.data.ndim >= 2:
                        return "image"
        except OSError as exc:
            raise XstackError(f"{path}: cannot read as FITS ({exc})") from None
    return "catalog"


def _load_catalog(model: Any) -> dict[str, np.ndarray]:
    from xstack.coords import read_catalog

    table = read_catalog(model, required_flux=True)
    ra = np.radians(np.asarray(table["ra"], dtype=np.float64))
    dec = np.radians(np.asarray(table["dec"], dtype=np.float64))
    fwhm = None
    cols = {c.lower(): c for c in table.colnames}
    if "fwhm_arcsec" in cols:
        fwhm = np.asarray(table[cols["fwhm_arcsec"]], dtype=np.float64)
        bad = np.flatnonzero(~np.isfinite(fwhm) | (fwhm < 0))
        if bad.size:
            raise XstackError(f"{model}: row {bad[0] + 1}: fwhm_arcsec must be finite and >= 0")
        fwhm = fwhm * _ARCSEC
    return {"ra": ra, "dec": dec, "flux": np.asarray(table["flux"], dtype=np.float64), "fwhm": fwhm}


def _load_image(model: Any) -> dict[str, Any]:
    from xstack.imaging.fitsio import grid_of, read_image

    data, _, header = read_image(model)
    grid = grid_of(header)
    unit = str(header.get("BUNIT", "")).strip().lower().replace(" ", "")
    if "beam" in unit:
        raise XstackError(f"{model}: BUNIT is {header['BUNIT']!r}; a CLEAN model image in "
                          "Jy/pixel is needed (the .model.fits of xstack image), not an image")
    if grid["nx"] % 2 or grid["ny"] % 2 or min(grid["nx"], grid["ny"]) < 32:
        raise XstackError(f"{model}: model image must have even sizes >= 32")
    cx, cy = grid["crpix"]
    if abs(cx - (grid["nx"] // 2 + 1)) > 1e-6 or abs(cy - (grid["ny"] // 2 + 1)) > 1e-6:
        raise XstackError(f"{model}: reference pixel ({cx}, {cy}) is not the image center "
                          f"({grid['nx'] // 2 + 1}, {grid['ny'] // 2 + 1}); grid does not match")
    if not np.all(np.isfinite(data)):
        raise XstackError(f"{model}: model image has non-finite pixels")
    return {"data": data, **grid}


def _catalog_block(vis: np.ndarray, uvw: np.ndarray, *, freq: np.ndarray, pols: list[int],
                   l: np.ndarray, m: np.ndarray, n1: np.ndarray, flux: np.ndarray,
                   att: np.ndarray | None, fwhm: np.ndarray | None) -> np.ndarray:
    nt, nb, nf, _ = vis.shape
    flat = uvw.reshape(-1, 3)
    good = np.all(np.isfinite(flat), axis=1)
    model = np.zeros((flat.shape[0], nf), dtype=np.complex128)
    if good.any() and flux.size:
        try:
            from xstack.sim.kernels import model_visibilities

            model[good] = model_visibilities(flat[good], freq, l, m, n1, flux, attenuation=att,
                                             fwhm=fwhm, parallel=False)
        except ImportError:  # pragma: no cover - the simulation stage is optional
            from xstack.imaging.kernels import point_source_visibilities

            model[good] = point_source_visibilities(flat[good], freq, l, m, n1, flux, att, fwhm)
    return _subtract_block(vis, model.reshape(nt, nb, nf), pols)


def _image_block(vis: np.ndarray, uvw: np.ndarray, *, freq: np.ndarray, pols: list[int],
                 image: np.ndarray, cell_arcsec: float, epsilon: float) -> np.ndarray:
    from xstack.imaging.image import predict

    model = predict(image, cell_arcsec, uvw, freq, epsilon=epsilon, nthreads=1)
    return _subtract_block(vis, model, pols)


def _subtract_block(vis: np.ndarray, model: np.ndarray, pols: list[int]) -> np.ndarray:
    out = vis.copy()
    for p in pols:
        out[..., p] = (vis[..., p].astype(np.complex128) - model).astype(vis.dtype)
    return out


def subtract(data: Any, model: Any, out: str | os.PathLike, *, overwrite: bool = False,
             progress: bool = False, epsilon: float = 1e-7, primary_beam: str | None = "auto",
             autocorrelations: bool = False) -> Path:
    """Subtract a model from every partition of a store; write the residual store.

    Parameters
    ----------
    data
        Input store or MeasurementSet path, DataTree, Dataset or dict of Datasets (any input
        of :func:`xstack._inputs.partitions`).
    model
        Component catalog (path or astropy Table; columns ra, dec, flux [Jy], optional
        fwhm_arcsec) or a CLEAN model FITS image (Jy/pixel) on a SIN grid whose reference
        pixel is the image center and whose center is the data's phase center.
    out
        Output ``.zarr`` store (same schema and partitions; VISIBILITY replaced).
    overwrite
        Replace an existing ``out``.
    progress
        Progress bar on stderr while writing.
    epsilon
        ducc0 accuracy for model images.
    primary_beam
        Catalog models only: ``"auto"`` (default; also ``None``: the telescope's standard
        beam), ``"none"`` (no attenuation), ``"airy"`` or ``"gaussian"``.
    autocorrelations
        Subtract the model from autocorrelation baselines too. Off by default: they hold an
        antenna's system power, not the sky, and are copied unchanged.

    Raises
    ------
    XstackError
        Bad model (missing columns, grid not matching the phase center, Jy/beam units...);
        checked for every partition before anything is written.
    """
    import dask.array as da

    from xstack._atomic import check_output
    from xstack._inputs import is_ms, open_input, partitions
    from xstack.beams import dish_diameter, standard_beam
    from xstack.coords import angular_separation, radec_to_lmn
    from xstack.schema import validate_store, write_store

    check_output(out, overwrite)
    if isinstance(data, (str, os.PathLike)):
        tree = open_input(data)
        root_attrs = dict(tree.attrs) if is_ms(data) else validate_store(data)
        if Path(out).resolve() == Path(data).resolve():
            raise XstackError("output store must differ from the input store")
        data = tree
    else:
        root_attrs = dict(data.attrs) if isinstance(data, xr.DataTree) else {}
    parts = partitions(data)
    kind = _model_kind(model)
    spec = _load_catalog(model) if kind == "catalog" else _load_image(model)
    result: dict[str, xr.Dataset] = {}
    for name, ds in parts:
        pols = [i for i, p in enumerate(ds["polarization"].values) if str(p).upper() in PARALLEL_HANDS]
        if not pols:
            raise XstackError(f"{name}: no parallel-hand polarization to subtract a Stokes I model from")
        freq = np.asarray(ds["frequency"].values, dtype=np.float64)
        ra0, dec0 = (float(x) for x in ds.attrs["phase_center"])
        vis = ds["VISIBILITY"].data
        uvw = ds["UVW"].data
        if not isinstance(vis, da.Array):
            vis = da.from_array(vis, chunks=(max(1, vis.shape[0] // 4 or 1), -1, -1, -1))
        if not isinstance(uvw, da.Array):
            uvw = da.from_array(uvw)
        uvw = uvw.rechunk((vis.chunks[0], vis.chunks[1], 3))
        if kind == "catalog":
            l, m, _, n1 = radec_to_lmn(spec["ra"], spec["dec"], ra0, dec0)
            sep = angular_separation(ra0, dec0, spec["ra"], spec["dec"])
            dish = dish_diameter(ds)
            model = None if primary_beam in (None, "auto") else primary_beam
            beam = standard_beam(str(ds.attrs.get("telescope_name", "")), dish, model=model)
            att = beam(sep[:, None], freq[None, :])
            # sources behind the sky (n < 0) or outside the beam's main lobe contribute nothing
            keep = (np.hypot(l, m) < 1.0) & np.any(att > 0, axis=1)
            kwargs = dict(freq=freq, pols=pols, l=l[keep], m=m[keep], n1=n1[keep],
                          flux=spec["flux"][keep], att=att[keep],
                          fwhm=None if spec["fwhm"] is None else spec["fwhm"][keep])
            func = _catalog_block
        else:
            offset = angular_separation(ra0, dec0, *spec["center"])
            if offset > 1e-3 * spec["cell_arcsec"] * _ARCSEC:
                raise XstackError(
                    f"model image center is {offset / _ARCSEC:.3f} arcsec from the phase center of "
                    f"{name}: the grid does not match the data (image that partition's pointing)")
            kwargs = dict(freq=freq, pols=pols, image=spec["data"], cell_arcsec=spec["cell_arcsec"],
                          epsilon=epsilon)
            func = _image_block
        resid = da.blockwise(func, "tbfp", vis, "tbfp", uvw, "tbx", dtype=vis.dtype,
                             concatenate=True, **kwargs)
        auto = autocorrelation_mask(ds)
        if auto.any() and not autocorrelations:
            resid = da.where(auto[None, :, None, None], vis, resid)
        new = ds.copy()
        new["VISIBILITY"] = (ds["VISIBILITY"].dims, resid, dict(ds["VISIBILITY"].attrs))
        new.attrs["subtracted_model"] = str(model) if not hasattr(model, "colnames") else "table"
        new.attrs["subtracted_model_kind"] = kind
        result[name] = new
    attrs = {k: v for k, v in root_attrs.items() if not k.startswith("xstack_") and k != "partitions"}
    attrs["subtracted_model"] = str(model) if not hasattr(model, "colnames") else "table"
    return write_store(result, out, kind=str(root_attrs.get("xstack_kind", "processing_set")),
                       overwrite=overwrite, attrs=attrs, progress=progress, description="subtracting")
