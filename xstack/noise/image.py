"""Image-domain noise and bias of a stack: the same four methods on a (residual) image.

The image-stacking estimator used here is the weighted mean of the pixel values at the
positions (nearest pixel), each divided by the primary-beam attenuation A_k when a beam is
used: F = sum_k w_k I(x_k) / A_k / sum_k w_k (``xstack imstack --method mean`` without
sub-pixel alignment). Monte Carlo injection is analytic, as in the uv-domain: a fake source
j of flux S_j adds S_j A_j PSF(x - x_j) to the image (PSF peak 1, same pixel grid), so the
stack of realisation r gains sum_k w_k sum_{j in r} S_j A_j PSF(x_k - x_j) / A_k / sum w.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from xstack.errors import XstackError


def _beam_values(info: Any, primary_beam: Any, cutoff: float):
    from xstack.beams import PrimaryBeam, standard_beam

    if primary_beam in (None, "none"):
        return None
    if isinstance(primary_beam, PrimaryBeam):
        return primary_beam
    tel = (info.telescope or "").strip()
    if not tel or info.frequency_hz is None:
        raise XstackError(f"{info.name}: primary beam {primary_beam!r} needs TELESCOP and a "
                          "frequency in the image header (or primary_beam='none')")
    dish = {"ALMA": 12.0, "VLA": 25.0, "EVLA": 25.0, "JVLA": 25.0}.get(tel.upper(), 25.0)
    model = None if primary_beam == "auto" else primary_beam
    return standard_beam(tel, dish, model=model, cutoff=cutoff)


def estimate_noise_image(image: Any, positions: Any, *, method: str, realizations: int,
                         flux: Any, min_separation_arcsec: float | None, avoid: Any, seed: int,
                         weighting: str, primary_beam: Any, pb_cutoff: float,
                         field_radius_arcsec: float | None, psf: Any = None):
    """Image-domain counterpart of :func:`xstack.noise.estimate.estimate_noise`."""
    from xstack.coords import angular_separation
    from xstack.imstack.io import psf_path_for, read_image
    from xstack.noise.estimate import NoiseResult, _injected_fluxes, _positions_from
    from xstack.noise.positions import ARCSEC, random_positions

    info = read_image(image)
    img = np.asarray(info.data, dtype=np.float64)
    ny, nx = img.shape
    ra_t, dec_t, cat = _positions_from(positions)
    beam = _beam_values(info, "auto" if primary_beam is None else primary_beam, pb_cutoff)
    pra, pdec = np.radians(info.pointing_deg[0]), np.radians(info.pointing_deg[1])

    def pix(ra, dec):
        x, y = info.wcs.world_to_pixel_values(np.degrees(ra), np.degrees(dec))
        return np.rint(y).astype(np.int64), np.rint(x).astype(np.int64)

    def atten(ra, dec):
        if beam is None:
            return np.ones(np.shape(ra))
        return np.asarray(beam(angular_separation(ra, dec, pra, pdec), info.frequency_hz))

    def usable(ra, dec):
        iy, ix = pix(ra, dec)
        ok = (iy >= 0) & (iy < ny) & (ix >= 0) & (ix < nx)
        ok[ok] &= np.isfinite(img[iy[ok], ix[ok]])
        if beam is not None:
            ok &= atten(ra, dec) >= max(beam.cutoff, 1e-12)
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
        return float(np.sum(w * img[iy, ix] / atten(ra, dec)) / np.sum(w))

    ra_u, dec_u, w_u = ra_t[ok_t], dec_t[ok_t], weights(ra_t[ok_t], dec_t[ok_t], w_base[ok_t])
    target = stack(ra_u, dec_u, w_u)
    n = ra_u.size
    rng = np.random.default_rng(seed)
    extra: dict[str, Any] = {"weighting": weighting, "image": info.name, "seed": int(seed)}
    if method == "analytic":
        finite = img[np.isfinite(img)]
        sigma_map = float(1.4826 * np.median(np.abs(finite - np.median(finite))))
        sig_k = sigma_map / atten(ra_u, dec_u)
        noise = float(1.0 / np.sqrt(np.sum(1.0 / sig_k**2)))
        wn = w_u / w_u.sum()
        extra.update({"sigma_map_jy_per_beam": sigma_map,
                      "estimator_noise_jy": float(np.sqrt(np.sum(wn**2 * sig_k**2)))})
        return NoiseResult("analytic", noise, None, 0, np.zeros(0), None, target, n,
                           domain="image", extra=extra)
    if method == "bootstrap":
        vals = np.empty(realizations)
        for r in range(realizations):
            idx = rng.integers(0, n, n)
            vals[r] = stack(ra_u[idx], dec_u[idx], w_u[idx])
        return NoiseResult("bootstrap", float(np.std(vals, ddof=1)), float(np.mean(vals) - target),
                           realizations, vals, None, target, n, domain="image", extra=extra)
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
                                           min_separation=min_sep, rng=rng)
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
        return NoiseResult("random", float(np.std(vals, ddof=1)), float(np.mean(vals)),
                           realizations, vals, None, target, n, domain="image", extra=extra,
                           positions_deg=pos)
    return NoiseResult("mc", float(np.std(vals, ddof=1)), float(np.mean(vals - injected)),
                       realizations, vals, injected, target, n, domain="image", extra=extra,
                       positions_deg=pos)
