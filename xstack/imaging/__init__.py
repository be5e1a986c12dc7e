"""Imaging, deconvolution and model subtraction (ducc0 w-gridder, Högbom/Clark CLEAN).

Modules: :mod:`~xstack.imaging.kernels` (numpy/numba kernels), :mod:`~xstack.imaging.image`
(``make_image``, ``predict``), :mod:`~xstack.imaging.clean` (``clean``, ``clean_data``),
:mod:`~xstack.imaging.subtract` (``subtract``), :mod:`~xstack.imaging.fitsio` (FITS I/O).
See ``docs/imaging.md``.
"""
