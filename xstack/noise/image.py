"""Image-domain noise and bias of a stack: the same four methods on a (residual) image.

The image-stacking estimator used here measures primary-beam corrected fluxes, like
``xstack imstack`` (one convention, docs/conventions.md): the weighted mean of the pixel
values at the positions (nearest pixel), each divided by the primary-beam attenuation A_k
when the image is not corrected, used as is when it is: F = sum_k w_k I_c(x_k) / sum_k w_k
with I_c = I / A (uncorrected image I) or the corrected image itself. Whether the image is
corrected is read from its header (``XSPBCOR``) and A from the beam file it names
(``XSPBFILE``: a mosaic's effective beam) unless ``primary_beam`` / ``image_corrected`` say
otherwise. A position is used when it is inside the field by the one rule of every stage
(:func:`xstack.beams.inside_field`, at the highest frequency of the image's band), so the
image-domain methods admit the positions the uv-domain ones admit. Monte Carlo injection is
analytic, as in the uv-domain: a fake source j of flux
S_j adds S_j A_j PSF(x - x_j) to the uncorrected image (PSF peak 1, same pixel grid), so the
corrected value at x_k gains sum_j S_j A_j PSF(x_k - x_j) / A_k.

:func:`estimate_noise_image` runs in the phases of every stage: load (image, beam, PSF,
targets) -> plan (random draws) -> compute (stacks) -> assemble (the result).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from xstack.errors import XstackError

if TYPE_CHECKING:
    from xstack.noise.estimate import NoiseOptions, NoiseResult


def estimate_noise_image(image: Any, positions: Any, options: NoiseOptions) -> NoiseResult:
    """Image-domain counterpart of :func:`xstack.noise.estimate.estimate_noise`.

    ``options.primary_beam``: ``None``/``"auto"`` (the image's own beam: ``XSPBFILE``, else
    the telescope's standard beam at its pointing), a model name, ``"none"`` (A = 1), a
    :class:`~xstack.beams.PrimaryBeam` or a PB FITS image; ``options.image_corrected``:
    whether the image is primary-beam corrected (default: its ``XSPBCOR``; an image that
    says nothing is used as is, with a warning). ``extra["primary_beam"]`` records what was
    used.
    """
    inputs = _ImageInputs(image, positions, options)
    plan = _plan(inputs, options)
    measured = _compute(inputs, plan, options)
    return _assemble(inputs, plan, measured, options)


class _ImageInputs:
    """The image, its beam convention, the PSF (mc) and the targets on it (pixels read)."""

    def __init__(self, image: Any, positions: Any, options: NoiseOptions):
        from xstack.imstack.io import image_beam, read_image
        from xstack.noise.estimate import _positions_from

        pb = options.primary_beam
        self.info = info = read_image(image)
        self.img = np.asarray(info.data, dtype=np.float64)
        self.ra_t, self.dec_t, self.cat = _positions_from(positions)
        self.conv = conv = image_beam(
            info, None if pb in (None, "auto") else pb, options.image_corrected,
            cutoff=options.pb_cutoff,
            how_to_state="image_corrected=True/False (or XSPBCOR = T/F in its header)")
        if conv.values is None and (options.weighting == "pb" or not conv.corrected):
            raise XstackError(conv.missing or f"{info.name}: no primary beam known; give "
                              "primary_beam=", option="primary_beam")
        self.beam = conv.values  # (ra_deg, dec_deg) -> A, or None (A = 1, corrected image)
        self.ok_t = self.usable(self.ra_t, self.dec_t)
        if not self.ok_t.any():
            raise XstackError(f"{info.name}: no target lies on the image (inside the beam cutoff)")
        self.w_base = np.ones(self.ra_t.size)
        if options.weighting == "column":
            if self.cat is None or "weight" not in self.cat.colnames:
                raise XstackError("weighting='column' needs a catalog with a weight column")
            self.w_base = np.asarray(self.cat["weight"], dtype=np.float64)
        self.weighting = options.weighting
        ok = self.ok_t
        self.ra_u, self.dec_u = self.ra_t[ok], self.dec_t[ok]
        self.w_u = self.weights(self.ra_u, self.dec_u, self.w_base[ok])
        self.psf = _read_psf(info, options.psf) if options.method == "mc" else None

    def pix(self, ra: np.ndarray, dec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest pixel (iy, ix) of positions in radians."""
        x, y = self.info.wcs.world_to_pixel_values(np.degrees(ra), np.degrees(dec))
        return np.rint(y).astype(np.int64), np.rint(x).astype(np.int64)

    def atten(self, ra: np.ndarray, dec: np.ndarray) -> np.ndarray:
        """Primary-beam attenuation A (1 where no beam is known)."""
        if self.beam is None:
            return np.ones(np.shape(ra))
        return np.asarray(self.beam(np.degrees(ra), np.degrees(dec)), dtype=np.float64)

    def corr(self, ra: np.ndarray, dec: np.ndarray) -> np.ndarray:
        """What a pixel value is divided by to give the corrected flux (1 if corrected)."""
        return np.ones(np.shape(ra)) if self.conv.corrected else self.atten(ra, dec)

    def usable(self, ra: np.ndarray, dec: np.ndarray) -> np.ndarray:
        """On the image, on a finite pixel and inside the field."""
        ny, nx = self.img.shape
        iy, ix = self.pix(ra, dec)
        ok = (iy >= 0) & (iy < ny) & (ix >= 0) & (ix < nx)
        ok[ok] &= np.isfinite(self.img[iy[ok], ix[ok]])
        if self.conv.inside is not None:
            # the one rule of every stage (xstack.beams.inside_field at the band edge)
            ok &= np.asarray(self.conv.inside(np.degrees(ra), np.degrees(dec)), dtype=bool)
        return ok

    def weights(self, ra: np.ndarray, dec: np.ndarray, base: np.ndarray) -> np.ndarray:
        """Position weights: A^2 (pb) or the given ones."""
        if self.weighting == "pb":
            return self.atten(ra, dec) ** 2
        return base

    def stack(self, ra: np.ndarray, dec: np.ndarray, w: np.ndarray) -> float:
        """The stacked (primary-beam corrected) flux at the positions, Jy."""
        iy, ix = self.pix(ra, dec)
        return float(np.sum(w * self.img[iy, ix] / self.corr(ra, dec)) / np.sum(w))


def _read_psf(info: Any, psf: Any) -> tuple[np.ndarray, tuple[int, ...]]:
    """The PSF (peak 1) and its peak pixel: ``psf`` or ``X.psf.fits`` beside the image."""
    from xstack.imstack.io import psf_path_for

    if psf is None and info.path is not None:
        cand = psf_path_for(info.path)
        psf = cand if cand.exists() else None
    if psf is None:
        raise XstackError(f"{info.name}: the mc method needs the PSF (dirty beam) image "
                          "(psf=..., or X.psf.fits beside the image)")
    from xstack.fit.imfit import read_psf

    P = read_psf(psf)
    if P.ndim != 2:
        raise XstackError(f"the PSF must be a 2-D image, got shape {P.shape}")
    P = np.where(np.isfinite(P), P, 0.0)
    pc = np.unravel_index(np.argmax(P), P.shape)
    return P / P[pc], pc


@dataclass
class _ImagePlan:
    """The random draws: bootstrap resamples, or random positions with the permutations of
    the weights and injected fluxes (in the generator's order of the original loop)."""

    boot_idx: list[np.ndarray]
    r_ra: np.ndarray | None = None
    r_dec: np.ndarray | None = None
    perm_w: list[np.ndarray] | None = None
    perm_s: list[np.ndarray] | None = None
    min_sep: float | None = None


def _plan(inputs: _ImageInputs, options: NoiseOptions) -> _ImagePlan:
    """Every realisation's positions (and resamples), from ``options.seed``."""
    rng = np.random.default_rng(options.seed)
    n, R = inputs.ra_u.size, options.realizations
    if options.method == "analytic":
        return _ImagePlan(boot_idx=[])
    if options.method == "bootstrap":
        return _ImagePlan(boot_idx=[rng.integers(0, n, n) for _ in range(R)])
    from xstack.noise.positions import ARCSEC

    info = inputs.info
    bmaj = (info.beam_arcsec[0] * ARCSEC) if info.beam_arcsec else None
    if options.min_separation_arcsec is not None:
        min_sep = float(options.min_separation_arcsec) * ARCSEC
    else:
        min_sep = 3.0 * bmaj if bmaj else 0.0
    r_ra, r_dec = _random_positions(inputs, options, rng, min_sep)
    perm_w, perm_s = [], []
    for _ in range(R):
        perm_w.append(rng.permutation(n))
        if options.method == "mc":
            perm_s.append(rng.permutation(n))
    return _ImagePlan(boot_idx=[], r_ra=r_ra, r_dec=r_dec, perm_w=perm_w, perm_s=perm_s,
                      min_sep=min_sep)


def _random_positions(inputs: _ImageInputs, options: NoiseOptions, rng: np.random.Generator,
                      min_sep: float) -> tuple[np.ndarray, np.ndarray]:
    """(R, n) random positions on usable pixels inside the largest usable disc around the
    pointing, within the targets' hull."""
    from xstack.coords import angular_separation
    from xstack.noise.estimate import _positions_from
    from xstack.noise.positions import ARCSEC, random_positions

    info, ra_u, dec_u = inputs.info, inputs.ra_u, inputs.dec_u
    n, R = ra_u.size, options.realizations
    pra, pdec = np.radians(info.pointing_deg[0]), np.radians(info.pointing_deg[1])
    if options.field_radius_arcsec is not None:
        radius = float(options.field_radius_arcsec) * ARCSEC
    else:
        radius = float(angular_separation(ra_u, dec_u, pra, pdec).max()) * 1.02 + 1e-9
    av_ra, av_dec = [inputs.ra_t], [inputs.dec_t]
    if options.avoid is not None:
        a_ra, a_dec, _ = _positions_from(options.avoid)
        av_ra.append(a_ra)
        av_dec.append(a_dec)
    r_ra = np.empty((R, n))
    r_dec = np.empty((R, n))
    for r in range(R):
        got_ra, got_dec = np.zeros(0), np.zeros(0)
        for _ in range(20):
            c_ra, c_dec = random_positions(n, 1, np.array([[pra, pdec]]), np.array([radius]),
                                           avoid_ra=np.concatenate(av_ra + [got_ra]),
                                           avoid_dec=np.concatenate(av_dec + [got_dec]),
                                           min_separation=min_sep, rng=rng,
                                           region="hull", region_targets=(ra_u, dec_u))
            keep = inputs.usable(c_ra[0], c_dec[0])
            got_ra = np.concatenate([got_ra, c_ra[0][keep]])[:n]
            got_dec = np.concatenate([got_dec, c_dec[0][keep]])[:n]
            if got_ra.size >= n:
                break
        if got_ra.size < n:
            raise XstackError(f"{info.name}: cannot place {n} random positions on the image "
                              "inside the beam (too dense or image too small)")
        r_ra[r], r_dec[r] = got_ra, got_dec
    return r_ra, r_dec


def _compute(inputs: _ImageInputs, plan: _ImagePlan, options: NoiseOptions) -> dict[str, Any]:
    """The stacks: target flux, and per method the map noise or the realisations' values."""
    target = inputs.stack(inputs.ra_u, inputs.dec_u, inputs.w_u)
    out: dict[str, Any] = {"target": target}
    if options.method == "analytic":
        out["sigma_map"] = _sigma_map(inputs)
    elif options.method == "bootstrap":
        out["values"] = np.array([inputs.stack(inputs.ra_u[i], inputs.dec_u[i], inputs.w_u[i])
                                  for i in plan.boot_idx])
    else:
        out["values"], out["injected"] = _realizations(inputs, plan, options, target)
    return out


def _sigma_map(inputs: _ImageInputs) -> float:
    """Robust (MAD) noise of the flat (uncorrected) image I = I_c A over the covered pixels."""
    img, beam, conv = inputs.img, inputs.beam, inputs.conv
    flat = img
    if beam is not None:
        yy, xx = np.indices(img.shape)
        wra, wdec = inputs.info.wcs.pixel_to_world_values(xx.ravel(), yy.ravel())
        a_pix = np.asarray(beam(np.asarray(wra), np.asarray(wdec))).reshape(img.shape)
        flat = np.where(a_pix >= max(conv.cutoff, 1e-12), img, np.nan)
        if conv.corrected:
            flat = flat * a_pix
    finite = flat[np.isfinite(flat)]
    if finite.size == 0:
        raise XstackError(f"{inputs.info.name}: no finite pixel inside the primary beam")
    return float(1.4826 * np.median(np.abs(finite - np.median(finite))))


def _realizations(inputs: _ImageInputs, plan: _ImagePlan, options: NoiseOptions,
                  target: float) -> tuple[np.ndarray, np.ndarray | None]:
    """Stacked flux of every random realisation (mc: with the injected fakes) and, for mc,
    the flux a noiseless stack would give."""
    from xstack.noise.estimate import _injected_fluxes

    n, R = inputs.ra_u.size, options.realizations
    vals = np.empty(R)
    injected = None
    if options.method == "mc":
        s_fake = _injected_fluxes(options.flux, inputs.cat, inputs.ok_t, n)
        if s_fake is None:
            s_fake = np.full(n, max(target, 0.0))
        P, pc = inputs.psf
        injected = np.empty(R)
    w_ok = inputs.w_base[inputs.ok_t]
    for r in range(R):
        ra, dec = plan.r_ra[r], plan.r_dec[r]
        w = inputs.weights(ra, dec, w_ok[plan.perm_w[r]])
        vals[r] = inputs.stack(ra, dec, w)
        if options.method == "mc":
            s = s_fake[plan.perm_s[r]]
            A = inputs.atten(ra, dec)
            iy, ix = inputs.pix(ra, dec)
            dy = iy[:, None] - iy[None, :] + pc[0]
            dx = ix[:, None] - ix[None, :] + pc[1]
            inb = (dy >= 0) & (dy < P.shape[0]) & (dx >= 0) & (dx < P.shape[1])
            psfv = np.where(inb, P[np.clip(dy, 0, P.shape[0] - 1), np.clip(dx, 0, P.shape[1] - 1)],
                            0.0)
            # image value at k from all fakes j, then the stack's beam correction
            model_at_k = psfv @ (s * A)
            vals[r] += float(np.sum(w * model_at_k / A) / np.sum(w))
            injected[r] = float(np.sum(w * s) / np.sum(w))
    return vals, injected


def _assemble(inputs: _ImageInputs, plan: _ImagePlan, measured: dict[str, Any],
              options: NoiseOptions) -> NoiseResult:
    """The :class:`~xstack.noise.estimate.NoiseResult` of the image domain."""
    from xstack.noise.estimate import NoiseResult
    from xstack.noise.positions import ARCSEC

    target, n, R = measured["target"], inputs.ra_u.size, options.realizations
    extra: dict[str, Any] = {"weighting": options.weighting, "image": inputs.info.name,
                             "seed": options.seed, "primary_beam": inputs.conv.to_dict()}
    used = options.to_dict()  # the options, completed with what the run decided
    common = dict(target_flux_jy=target, n_positions=n, domain="image", extra=extra,
                  options=used)
    if options.method == "analytic":
        sigma_map = measured["sigma_map"]
        sig_k = sigma_map / inputs.atten(inputs.ra_u, inputs.dec_u)
        # the noise of the estimator actually used (weights w_u), as in the uv domain; the
        # inverse-variance optimum (eq. 6) for comparison
        wn = inputs.w_u / inputs.w_u.sum()
        noise = float(np.sqrt(np.sum(wn**2 * sig_k**2)))
        extra.update({"sigma_map_jy_per_beam": sigma_map,
                      "optimal_noise_jy": float(1.0 / np.sqrt(np.sum(1.0 / sig_k**2)))})
        return NoiseResult(method="analytic", noise_jy=noise, bias_jy=None, realizations=0,
                           **common)
    vals = measured["values"]
    if options.method == "bootstrap":
        return NoiseResult(method="bootstrap", noise_jy=float(np.std(vals, ddof=1)),
                           bias_jy=float(np.mean(vals) - target), realizations=R, values=vals,
                           **common)
    extra["min_separation_arcsec"] = used["min_separation_arcsec"] = float(plan.min_sep / ARCSEC)
    pos = np.degrees(np.stack([plan.r_ra, plan.r_dec], -1))
    if options.method == "random":
        return NoiseResult(method="random", noise_jy=float(np.std(vals, ddof=1)),
                           bias_jy=float(np.mean(vals)), realizations=R, values=vals,
                           positions_deg=pos, **common)
    injected = measured["injected"]
    return NoiseResult(method="mc", noise_jy=float(np.std(vals, ddof=1)),
                       bias_jy=float(np.mean(vals - injected)), realizations=R, values=vals,
                       injected=injected, positions_deg=pos, **common)
