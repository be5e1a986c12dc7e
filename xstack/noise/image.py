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
"""

from __future__ import annotations

from typing import Any

import numpy as np

from xstack.errors import XstackError


def estimate_noise_image(image: Any, positions: Any, *, method: str, realizations: int,
                         flux: Any, min_separation_arcsec: float | None, avoid: Any, seed: int,
                         weighting: str, primary_beam: Any, pb_cutoff: float,
                         field_radius_arcsec: float | None, psf: Any = None,
                         image_corrected: bool | None = None):
    """Image-domain counterpart of :func:`xstack.noise.estimate.estimate_noise`.

    ``primary_beam``: ``None``/``"auto"`` (the image's own beam: ``XSPBFILE``, else the
    telescope's standard beam at its pointing), a model name, ``"none"`` (A = 1), a
    :class:`~xstack.beams.PrimaryBeam` or a PB FITS image; ``image_corrected``: whether the
    image is primary-beam corrected (default: its ``XSPBCOR``; an image that says nothing is
    used as is, with a warning). ``extra["primary_beam"]`` records what was used.
    """
    from xstack.coords import angular_separation
    from xstack.imstack.io import image_beam, psf_path_for, read_image
    from xstack.noise.estimate import NoiseResult, _injected_fluxes, _positions_from
    from xstack.noise.positions import ARCSEC, random_positions

    info = read_image(image)
    img = np.asarray(info.data, dtype=np.float64)
    ny, nx = img.shape
    ra_t, dec_t, cat = _positions_from(positions)
    conv = image_beam(info, None if primary_beam in (None, "auto") else primary_beam,
                      image_corrected, cutoff=pb_cutoff,
                      how_to_state="image_corrected=True/False (or XSPBCOR = T/F in its header)")
    if conv.values is None and (weighting == "pb" or not conv.corrected):
        raise XstackError(conv.missing or f"{info.name}: no primary beam known; give primary_beam=",
                          option="primary_beam")
    beam = conv.values  # (ra_deg, dec_deg) -> A, or None (unknown: A = 1 for a corrected image)
    pra, pdec = np.radians(info.pointing_deg[0]), np.radians(info.pointing_deg[1])

    def pix(ra, dec):
        x, y = info.wcs.world_to_pixel_values(np.degrees(ra), np.degrees(dec))
        return np.rint(y).astype(np.int64), np.rint(x).astype(np.int64)

    def atten(ra, dec):
        if beam is None:
            return np.ones(np.shape(ra))
        return np.asarray(beam(np.degrees(ra), np.degrees(dec)), dtype=np.float64)

    def corr(ra, dec):
        """What a pixel value is divided by to give the corrected flux (1 if corrected)."""
        return np.ones(np.shape(ra)) if conv.corrected else atten(ra, dec)

    def usable(ra, dec):
        iy, ix = pix(ra, dec)
        ok = (iy >= 0) & (iy < ny) & (ix >= 0) & (ix < nx)
        ok[ok] &= np.isfinite(img[iy[ok], ix[ok]])
        if conv.inside is not None:
            # the one rule of every stage (xstack.beams.inside_field at the band edge)
            ok &= np.asarray(conv.inside(np.degrees(ra), np.degrees(dec)), dtype=bool)
        return ok

    ok_t = usable(ra_t, dec_t)
    if not ok_t.any():
        raise XstackError(f"{info.name}: no target lies on the image (inside the beam cutoff)")

    def weights(ra, dec, base):
        if weighting == "pb":
            return atten(ra, dec) ** 2
        return base

    w_base = np.ones(ra_t.size)
    if weighting == "column":
        if cat is None or "weight" not in cat.colnames:
            raise XstackError("weighting='column' needs a catalog with a weight column")
        w_base = np.asarray(cat["weight"], dtype=np.float64)

    def stack(ra, dec, w):
        iy, ix = pix(ra, dec)
        return float(np.sum(w * img[iy, ix] / corr(ra, dec)) / np.sum(w))

    ra_u, dec_u, w_u = ra_t[ok_t], dec_t[ok_t], weights(ra_t[ok_t], dec_t[ok_t], w_base[ok_t])
    target = stack(ra_u, dec_u, w_u)
    n = ra_u.size
    rng = np.random.default_rng(seed)
    extra: dict[str, Any] = {"weighting": weighting, "image": info.name, "seed": int(seed),
                             "primary_beam": conv.to_dict()}
    if method == "analytic":
        # the noise of the flat (uncorrected) image I = I_c A, from the covered pixels
        flat = img
        if beam is not None:
            yy, xx = np.indices(img.shape)
            wra, wdec = info.wcs.pixel_to_world_values(xx.ravel(), yy.ravel())
            a_pix = np.asarray(beam(np.asarray(wra), np.asarray(wdec))).reshape(img.shape)
            flat = np.where(a_pix >= max(conv.cutoff, 1e-12), img, np.nan)
            if conv.corrected:
                flat = flat * a_pix
        finite = flat[np.isfinite(flat)]
        if finite.size == 0:
            raise XstackError(f"{info.name}: no finite pixel inside the primary beam")
        sigma_map = float(1.4826 * np.median(np.abs(finite - np.median(finite))))
        sig_k = sigma_map / atten(ra_u, dec_u)
        # the noise of the estimator actually used (weights w_u), as in the uv domain; the
        # inverse-variance optimum (eq. 6) for comparison
        wn = w_u / w_u.sum()
        noise = float(np.sqrt(np.sum(wn**2 * sig_k**2)))
        extra.update({"sigma_map_jy_per_beam": sigma_map,
                      "optimal_noise_jy": float(1.0 / np.sqrt(np.sum(1.0 / sig_k**2)))})
        return NoiseResult(method="analytic", noise_jy=noise, bias_jy=None, realizations=0,
                           target_flux_jy=target, n_positions=n, domain="image", extra=extra)
    if method == "bootstrap":
        vals = np.empty(realizations)
        for r in range(realizations):
            idx = rng.integers(0, n, n)
            vals[r] = stack(ra_u[idx], dec_u[idx], w_u[idx])
        return NoiseResult(method="bootstrap", noise_jy=float(np.std(vals, ddof=1)),
                           bias_jy=float(np.mean(vals) - target), realizations=realizations,
                           values=vals, target_flux_jy=target, n_positions=n, domain="image",
                           extra=extra)
    # random / mc: positions inside the largest usable disc around the pointing
    bmaj = (info.beam_arcsec[0] * ARCSEC) if info.beam_arcsec else None
    if min_separation_arcsec is not None:
        min_sep = float(min_separation_arcsec) * ARCSEC
    else:
        min_sep = 3.0 * bmaj if bmaj else 0.0
    if field_radius_arcsec is not None:
        radius = float(field_radius_arcsec) * ARCSEC
    else:
        radius = float(angular_separation(ra_u, dec_u, pra, pdec).max()) * 1.02 + 1e-9
    av_ra, av_dec = [ra_t], [dec_t]
    if avoid is not None:
        a_ra, a_dec, _ = _positions_from(avoid)
        av_ra.append(a_ra)
        av_dec.append(a_dec)
    r_ra = np.empty((realizations, n))
    r_dec = np.empty((realizations, n))
    for r in range(realizations):
        got_ra, got_dec = np.zeros(0), np.zeros(0)
        for _ in range(20):
            c_ra, c_dec = random_positions(n, 1, np.array([[pra, pdec]]), np.array([radius]),
                                           avoid_ra=np.concatenate(av_ra + [got_ra]),
                                           avoid_dec=np.concatenate(av_dec + [got_dec]),
                                           min_separation=min_sep, rng=rng,
                                           region="hull", region_targets=(ra_u, dec_u))
            keep = usable(c_ra[0], c_dec[0])
            got_ra = np.concatenate([got_ra, c_ra[0][keep]])[:n]
            got_dec = np.concatenate([got_dec, c_dec[0][keep]])[:n]
            if got_ra.size >= n:
                break
        if got_ra.size < n:
            raise XstackError(f"{info.name}: cannot place {n} random positions on the image "
                              "inside the beam (too dense or image too small)")
        r_ra[r], r_dec[r] = got_ra, got_dec
    vals = np.empty(realizations)
    injected = None
    s_fake = np.zeros(n)
    if method == "mc":
        s_fake = _injected_fluxes(flux, cat, ok_t, n)
        if s_fake is None:
            s_fake = np.full(n, max(target, 0.0))
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
        P = P / P[pc]
        injected = np.empty(realizations)
    for r in range(realizations):
        w = weights(r_ra[r], r_dec[r], w_base[ok_t][rng.permutation(n)])
        vals[r] = stack(r_ra[r], r_dec[r], w)
        if method == "mc":
            s = s_fake[rng.permutation(n)]
            A = atten(r_ra[r], r_dec[r])
            iy, ix = pix(r_ra[r], r_dec[r])
            dy = iy[:, None] - iy[None, :] + pc[0]
            dx = ix[:, None] - ix[None, :] + pc[1]
            inb = (dy >= 0) & (dy < P.shape[0]) & (dx >= 0) & (dx < P.shape[1])
            psfv = np.where(inb, P[np.clip(dy, 0, P.shape[0] - 1), np.clip(dx, 0, P.shape[1] - 1)],
                            0.0)
            # image value at k from all fakes j, then the stack's beam correction
            model_at_k = psfv @ (s * A)
            vals[r] += float(np.sum(w * model_at_k / A) / np.sum(w))
            injected[r] = float(np.sum(w * s) / np.sum(w))
    extra["min_separation_arcsec"] = float(min_sep / ARCSEC)
    pos = np.degrees(np.stack([r_ra, r_dec], -1))
    if method == "random":
        return NoiseResult(method="random", noise_jy=float(np.std(vals, ddof=1)),
                           bias_jy=float(np.mean(vals)), realizations=realizations, values=vals,
                           target_flux_jy=target, n_positions=n, domain="image", extra=extra,
                           positions_deg=pos)
    return NoiseResult(method="mc", noise_jy=float(np.std(vals, ddof=1)),
                       bias_jy=float(np.mean(vals - injected)), realizations=realizations,
                       values=vals, injected=injected, target_flux_jy=target, n_positions=n,
                       domain="image", extra=extra, positions_deg=pos)
