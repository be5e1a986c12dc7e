"""A real VLA MeasurementSet: convert to a zarr processing set, inspect, image, export back.

Uses the EVLA observation shipped inside the ``pyuvdata==3.2.3`` wheel (installed with
``pip install -e '.[test]'``; the MS is read with python-casacore, never with pyuvdata's
own reader). Shows the data model (``xstack.open_store``: one xarray Dataset per
partition), a dirty image with a correct WCS, and the round trip back to an MS.

Run: ``python examples/real_vla_ms.py [OUTDIR]`` (a few seconds).
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

import xstack
from xstack.imaging.fitsio import write_image
from xstack.testing import real_ms


def main(outdir: Path) -> dict:
    outdir.mkdir(parents=True, exist_ok=True)
    ms = real_ms("evla", outdir)  # a copy: xstack never modifies its inputs anyway
    store = xstack.convert_ms(ms, outdir / "evla.zarr", overwrite=True)
    tree = xstack.open_store(store)
    for name, ds in xstack.iter_partitions(tree):
        print(f"partition {name}: {dict(ds.sizes)}")
        print(f"  telescope {ds.attrs.get('telescope_name')}, "
              f"{ds.frequency.size} channels {ds.frequency.values[0] / 1e9:.4f}-"
              f"{ds.frequency.values[-1] / 1e9:.4f} GHz, polarizations {list(ds.polarization.values)}")
        flagged = float(ds.FLAG.mean().compute())
        print(f"  {flagged:.1%} of the visibilities flagged")

    image = xstack.make_image(tree, size=512, cell_arcsec=0.4, weighting="briggs", robust=0.5)
    path = write_image(outdir / "evla_dirty.fits", image.image, image.header, overwrite=True)
    peak = tuple(int(i) for i in np.unravel_index(np.nanargmax(np.abs(image.image)), image.image.shape))
    print(f"dirty image {path.name}: beam {image.beam[0]:.1f} x {image.beam[1]:.1f} arcsec, "
          f"reference pixel at the phase center {image.wcs.wcs.crval}, peak |I| at pixel {peak}")

    summary = {"beam_arcsec": image.beam[:2], "crval": tuple(image.wcs.wcs.crval)}
    back = xstack.export_ms(store, outdir / "evla_roundtrip.ms", overwrite=True)
    print(f"exported back to {back}")
    return summary


if __name__ == "__main__":
    with tempfile.TemporaryDirectory() as tmp:  # OUTDIR on the command line keeps the files
        main(Path(sys.argv[1] if len(sys.argv) > 1 else tmp))
