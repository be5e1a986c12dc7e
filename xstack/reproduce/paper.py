"""The paper's numbers and procedure choices, typed from Lindroos et al. 2015 (MNRAS 446, 3502).

Nothing here is read at run time from outside the package: the rows of Table 2
(``tab:simresults``) and the per-type choices of §2 and §4 are constants.
"""

from __future__ import annotations

import copy
from dataclasses import asdict, dataclass
from typing import Any

UJY = 1e-6
MJY = 1e-3


def _row(expected: float, expected_noise: float | None, uv: float, uv_scatter: float,
         uv_snr: float, im: float, im_scatter: float, im_snr: float, unit: float
         ) -> dict[str, Any]:
    return {"expected_flux_jy": expected * unit,
            "expected_noise_jy": None if expected_noise is None else expected_noise * unit,
            "uv_flux_jy": uv * unit, "uv_scatter_jy": uv_scatter * unit, "uv_snr": uv_snr,
            "image_flux_jy": im * unit, "image_scatter_jy": im_scatter * unit,
            "image_snr": im_snr}


#: Table 2 of the paper (``tab:simresults``): per data-set type, the expected value ± expected
#: noise (eq. 9 with sigma from the cleaned residual map), and the uv- and image-stacked flux
#: density ± scatter over 100 realisations with the SNR in brackets. Types 1-7 and 11 are in
#: µJy in the table, 8-10 in mJy; stored here in Jy. Type 7 has no expected noise in the table.
PAPER_TABLE2: dict[int, dict[str, Any]] = {
    1: _row(6.00, 0.47, 6.02, 0.38, 15.8, 5.89, 0.49, 12.0, UJY),
    2: _row(6.00, 0.47, 6.02, 0.38, 15.8, 5.73, 0.49, 11.7, UJY),
    3: _row(0.99, 0.12, 0.97, 0.12, 8.1, 0.93, 0.13, 7.2, UJY),
    4: _row(0.99, 0.13, 0.98, 0.12, 8.2, 0.94, 0.12, 7.8, UJY),
    5: _row(0.99, 0.12, 0.99, 0.13, 7.6, 0.94, 0.14, 6.7, UJY),
    6: _row(0.99, 0.15, 0.99, 0.16, 6.2, 0.91, 0.18, 5.1, UJY),
    7: _row(2.96, None, 2.96, 0.41, 7.2, 3.01, 0.54, 5.6, UJY),
    8: _row(1.00, 0.10, 0.98, 0.12, 8.2, 0.90, 0.11, 8.2, MJY),
    9: _row(1.00, 0.09, 1.00, 0.08, 12.5, 0.97, 0.09, 10.8, MJY),
    10: _row(0.20, 0.02, 0.20, 0.02, 10.0, 0.17, 0.03, 5.7, MJY),
    11: _row(0.99, 0.32, 1.00, 0.20, 5.0, 1.06, 0.32, 3.3, UJY),
}

#: Type 7's size fits (§4.1.7 "Extended target sources" and the caption of Fig. 8): the
#: uv fit gives 1.50 ± 0.2 arcsec (scatter 0.21 in Fig. 8), the image fit 1.55 ± 0.4 arcsec
#: (0.43 in Fig. 8); the true FWHM is 1.5 arcsec. The text's fluxes are 3.0 ± 0.4 µJy (uv)
#: and 3.0 ± 0.5 µJy (image).
PAPER_TYPE7_SIZES: dict[str, float] = {
    "true_fwhm_arcsec": 1.5,
    "uv_fwhm_arcsec": 1.50, "uv_fwhm_scatter_arcsec": 0.21,
    "image_fwhm_arcsec": 1.55, "image_fwhm_scatter_arcsec": 0.43,
}


@dataclass(frozen=True)
class Procedure:
    """What the paper does with one data-set type after simulating it.

    Attributes
    ----------
    cell_arcsec, size
        Image pixel size (arcsec) and size (pixels) of §2 (for type 9, of one pointing).
    clean_threshold_jy
        CLEAN threshold of the bright sources (Jy/beam), §2.
    clean_min_flux_jy
        Only bright sources at least this bright are CLEANed (type 5: 10 µJy); 0: all.
    uvmin_m
        uv-stacking uses only baselines longer than this (m): 5000 m for the VLA types with a
        realistic bright population (§4.1.5-4.1.7); None: all baselines.
    fit_size
        Flux and size by model fitting (type 7: Gaussian in uv, PSF-convolved Gaussian in the
        image) instead of the stacked flux.
    mosaic
        ``"joint"``: a contiguous mosaic imaged as one (8, 10); ``"pointings"``: each pointing
        imaged and CLEANed on its own (9); None: one pointing. Differs from the paper for
        8 and 10: the paper CLEANs the joint mosaic (CASA's mosaic gridding); xstack's CLEAN
        works on one pointing at a time (a joint CLEAN needs the mosaic's position-dependent
        PSF and beam), so every pointing is CLEANed and subtracted on its own as in type 9
        (:func:`xstack.reproduce.run.clean_subtract_mosaic`); only the image-stacked map is
        the joint (linear) mosaic, not CASA's, whose blurring the paper blames for type 8's
        20 % low image-stacked flux (§4.2.1).
    pointing_size
        Mosaics only: the size (pixels) of the image of one pointing that is CLEANed (types 8
        and 10: 256 pixels of 0.2", 51", twice the 25" primary-beam FWHM of a 12 m dish at
        230 GHz, as type 9's pointing images); None: ``size``. Left out of :meth:`to_dict`
        when None, so that the records of the single-pointing types keep their procedure.
    uv_weighting, image_weighting
        Position weights 1/sigma_k^2 (eq. 2) in both: sigma_k the local noise of the residual
        map around position k; uv-stacking uses "the same local noise estimators as in
        image-stacking" (§3.3). ALMA (8-10): ``"pb"``, sigma_k = 1/A_N(S_k) (§3.2).
    image_noise_estimator
        How the image stack measures sigma_k (``stack_images(noise_estimator=)``, on stamps
        of ~300 beam areas): ``"clipped"``, the estimator the uv stack's ``noise_image``
        weights use, so both stacks weigh the positions alike (§3.3: "the same local noise
        estimators"). Records made before it existed (no such key in their procedure) used
        the plain standard deviation on the 64-pixel stamp, which made type 6's image stack
        22 % low (docs/reproduction.md).
    image_noise_flat
        sigma_k is measured on the primary-beam corrected residual map times A, where the
        noise is flat, and divided by A at the position (both stacks; ``noise_flattened`` of
        :class:`xstack.imstack.ImstackResult`). Always True: it says how a record was made, as
        records made before it (no such key) measured it on the corrected map itself, where
        an ALMA pointing's noise rises 1/A across the ~300-beam stamp.
    thermal_noise_jy
        The thermal noise limit at the center of the full-size data set (Jy/beam): 2.1 µJy
        for the VLA types (§2.2; type 11 "similar", §2.4), 0.5 mJy for one ALMA pointing
        (type 9's map noise, §2.3.2). Sets the CLEAN threshold of scaled-down runs.
    epsilon
        ducc0 gridding accuracy of the images (not the paper's: a speed knob). Measured on a
        type-3 image (4000 x 4000, scale 0.05): 1e-4 instead of the default 1e-6 halves the
        time (11 s against 21 s) and changes no pixel by more than 5e-8 Jy/beam, 1/1400 of
        the image rms.
    """

    cell_arcsec: float
    size: int
    clean_threshold_jy: float
    clean_min_flux_jy: float = 0.0
    uvmin_m: float | None = None
    fit_size: bool = False
    mosaic: str | None = None
    uv_weighting: str = "sigma2"
    image_weighting: str = "sigma2"
    epsilon: float = 1e-4
    thermal_noise_jy: float = 2.1e-6
    pointing_size: int | None = None
    image_noise_estimator: str = "clipped"
    image_noise_flat: bool = True

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        if d["pointing_size"] is None:  # added later: earlier records lack it
            del d["pointing_size"]
        return d


_VLA_WIDE = dict(cell_arcsec=0.5, size=4000)
#: the wide VLA fields with Bondi et al. (2008) bright sources (types 5-7, 11): sources of
#: 10 µJy and more CLEANed to 50 µJy/beam, uv-stacked beyond 5000 m (§4.1.5)
_VLA_BRIGHT = dict(_VLA_WIDE, clean_threshold_jy=50e-6, clean_min_flux_jy=10e-6, uvmin_m=5000.0)
#: ALMA (§2.3): 0.2" pixels, CLEAN above 2 mJy to 2 mJy, 0.5 mJy/beam per pointing; position
#: weights sigma_k = 1/A_N(S_k) in both stacks (§3.2: the ALMA stamps are too small for a
#: local rms), i.e. W_k = A^2, xstack's ``"pb"`` weighting.
_ALMA = dict(cell_arcsec=0.2, clean_threshold_jy=2e-3, clean_min_flux_jy=2e-3,
             thermal_noise_jy=0.5e-3, uv_weighting="pb", image_weighting="pb")

#: The paper's per-type procedure (§2 for imaging and CLEAN, §4 for the uv cut and fits).
#: Type 3 is "based on type 2" (20 µJy threshold); type 4 raises it to 50 µJy and types 5-7
#: and 11 are imaged "in the same manner" as type 3/4; type 11 is "otherwise based on type 5",
#: and "for uv-stacking in data set 11 we are excluding the shortest baselines" (§5, sparse
#: array) without a length: type 5's 5000 m, the paper's only cut.
PROCEDURES: dict[int, Procedure] = {
    1: Procedure(cell_arcsec=0.25, size=1440, clean_threshold_jy=20e-6),
    2: Procedure(cell_arcsec=0.5, size=720, clean_threshold_jy=20e-6),
    3: Procedure(**_VLA_WIDE, clean_threshold_jy=20e-6),
    4: Procedure(**_VLA_WIDE, clean_threshold_jy=50e-6),
    5: Procedure(**_VLA_BRIGHT),
    6: Procedure(**_VLA_BRIGHT),
    7: Procedure(**_VLA_BRIGHT, fit_size=True),
    8: Procedure(**_ALMA, size=800, mosaic="joint", pointing_size=256),
    9: Procedure(**_ALMA, size=256, mosaic="pointings"),
    10: Procedure(**_ALMA, size=800, mosaic="joint", pointing_size=256),
    11: Procedure(**_VLA_BRIGHT),
}

TYPES = tuple(range(1, 12))


def paper_row(n: int) -> dict[str, Any]:
    """The paper's Table 2 row of type ``n`` (Jy; type 7 with its size fits), a fresh copy."""
    row = copy.deepcopy(PAPER_TABLE2[n])
    if n == 7:
        row["sizes"] = dict(PAPER_TYPE7_SIZES)
    return row
