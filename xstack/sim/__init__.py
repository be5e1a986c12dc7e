"""Scene simulator: the paper's simulated data sets written as xstack stores.

Modules: :mod:`~xstack.sim.kernels` (equation 1, numpy/numba), :mod:`~xstack.sim.arrays`
(antenna configurations and uvw geometry), :mod:`~xstack.sim.counts` (flux distributions),
:mod:`~xstack.sim.scene` (scene description and TOML loading), :mod:`~xstack.sim.simulate`
(dask wrapper and writing) and :mod:`~xstack.sim.presets` (the paper's types 1-11).
"""
