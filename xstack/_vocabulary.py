"""Shared vocabulary of the options: the names each stage accepts, and shared defaults.

One home for what both the library and the command line spell: the stage modules validate
against these tuples and the CLI offers them as ``choices`` (imported, never retyped). The
module imports nothing, so building the command-line parsers stays cheap. Public homes
re-export them: :data:`xstack.beams.DEFAULT_PB_CUTOFF`, ``xstack.uvstack.stack.WEIGHTINGS``...
"""

from __future__ import annotations

#: Default attenuation below which a position is taken to be outside a pointing
#: (public home: :data:`xstack.beams.DEFAULT_PB_CUTOFF`).
DEFAULT_PB_CUTOFF = 0.1

# uv-stacking (xstack.uvstack.stack)
UVSTACK_WEIGHTINGS = ("none", "pb", "sigma2", "column")
UVSTACK_ENGINES = ("auto", "antenna", "numba", "numpy", "nufft")
UVSTACK_ERRORS = ("auto", "weights", "empirical")
SMEARING_MODES = ("auto", "correct", "none")

# image-stacking (xstack.imstack)
IMSTACK_METHODS = ("mean", "median")
IMSTACK_WEIGHTINGS = ("sigma2", "pb", "none", "column")
SUBPIXEL_METHODS = ("fourier", "spline")
CUBE_FORMATS = ("zarr", "fits")
#: estimators of the local noise sigma_k (imstack and the uv stack's noise_image)
LOCAL_NOISE_ESTIMATORS = ("clipped", "mad", "std")

#: sigma of a Gaussian = MAD_TO_SIGMA x its median absolute deviation: 1 / Phi^-1(3/4)
MAD_TO_SIGMA = 1.482602218505602

# noise (xstack.noise.estimate)
NOISE_METHODS = ("analytic", "mc", "random", "bootstrap")
NOISE_ENGINES = ("auto", "antenna", "numba")
NOISE_WEIGHTINGS = ("none", "pb", "column")
#: primary-beam models by name: ``auto`` is the telescope's standard beam
#: (:func:`xstack.beams.standard_beam`); uvstack and imstack also take a beam FITS image
PRIMARY_BEAM_MODELS = ("auto", "airy", "gaussian", "none")
NOISE_PRIMARY_BEAMS = PRIMARY_BEAM_MODELS

# imaging (xstack.imaging)
IMAGE_WEIGHTINGS = ("natural", "uniform", "briggs")
CLEAN_ALGORITHMS = ("hogbom", "clark")
SUBTRACT_PRIMARY_BEAMS = PRIMARY_BEAM_MODELS

# fitting (xstack.fit)
FIT_MODELS = ("point", "gaussian")
NOISE_CORRELATIONS = ("psf", "residual", "none")

# spectral-line stacking (xstack.frames, xstack.uvstack.line): the frames line stacks are
# made in (TOPO data are converted per integration, xstack.frames.frame_ratio)
LINE_FRAMES = ("lsrk", "bary")
#: Frames of an image-cube line stack: the catalog's (the cube converted) or the cube's own.
CUBE_LINE_FRAMES = (*LINE_FRAMES, "cube")
#: How random line-noise targets take redshifts from the targets': permuted or resampled.
REDSHIFT_DRAWS = ("permute", "resample")
