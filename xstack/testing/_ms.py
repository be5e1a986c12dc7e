"""A generator of small but realistic MeasurementSets, written with python-casacore."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from xstack.coords import SPEED_OF_LIGHT, radec_to_lmn

#: Geodetic site (longitude deg, latitude deg, height m) and dish diameter of known arrays.
SITES = {
    "ALMA": (-67.754929, -23.029211, 5058.7, 12.0),
    "VLA": (-107.618283, 34.078749, 2124.0, 25.0),
    "EVLA": (-107.618283, 34.078749, 2124.0, 25.0),
    "MEERKAT": (21.443888, -30.713055, 1038.0, 13.5),
}

#: Paper field center (RA 3h49m10.99s, Dec -30 deg, J2000), radians.
DEFAULT_PHASE_CENTER = (np.deg2rad((3 + 49 / 60 + 10.99 / 3600) * 15.0), np.deg2rad(-30.0))

#: Astropy frame for a casacore direction reference (besides J2000/ICRS, treated as ICRS).
_ASTROPY_FRAMES = {"B1950": "fk4", "B1950_VLA": "fk4", "GALACTIC": "galactic"}


def _geodetic_to_ecef(lon_deg: float, lat_deg: float, height: float) -> np.ndarray:
    """WGS84 geodetic -> ECEF (ITRF) metres."""
    a, f = 6378137.0, 1.0 / 298.257223563
    e2 = f * (2 - f)
    lon, lat = np.deg2rad(lon_deg), np.deg2rad(lat_deg)
    n = a / np.sqrt(1 - e2 * np.sin(lat) ** 2)
    return np.array([(n + height) * np.cos(lat) * np.cos(lon),
                     (n + height) * np.cos(lat) * np.sin(lon),
                     (n * (1 - e2) + height) * np.sin(lat)])


def _enu_to_ecef_rotation(lon_deg: float, lat_deg: float) -> np.ndarray:
    """Matrix whose columns are the east, north, up unit vectors in ECEF."""
    lon, lat = np.deg2rad(lon_deg), np.deg2rad(lat_deg)
    east = [-np.sin(lon), np.cos(lon), 0.0]
    north = [-np.sin(lat) * np.cos(lon), -np.sin(lat) * np.sin(lon), np.cos(lat)]
    up = [np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)]
    return np.array([east, north, up]).T


def _earth_rotation_angle(mjd_seconds: np.ndarray) -> np.ndarray:
    """Earth rotation angle (radians), a good enough Greenwich sidereal angle for test data."""
    jd = mjd_seconds / 86400.0 + 2400000.5
    return 2 * np.pi * np.mod(0.7790572732640 + 1.00273781191135448 * (jd - 2451545.0), 1.0)


def uvw_from_itrf(baseline_xyz: np.ndarray, gha: np.ndarray, dec: float) -> np.ndarray:
    """UVW (metres) of ITRF baseline vectors (ANTENNA2 - ANTENNA1) at Greenwich hour angles.

    Thompson, Moran & Swenson eq. 4.1 with (X, Y, Z) the ECEF baseline components.
    """
    bx, by, bz = baseline_xyz[..., 0], baseline_xyz[..., 1], baseline_xyz[..., 2]
    sh, ch = np.sin(gha), np.cos(gha)
    sd, cd = np.sin(dec), np.cos(dec)
    u = sh * bx + ch * by
    v = -sd * ch * bx + sd * sh * by + cd * bz
    w = cd * ch * bx - cd * sh * by + sd * bz
    return np.stack([u, v, w], axis=-1)


def _phase_dir_in_frame(ra: float, dec: float, frame: str) -> tuple[float, float]:
    """Express an ICRS direction in a casacore reference frame (for frame-conversion tests)."""
    if frame in ("J2000", "ICRS"):
        return ra, dec
    from astropy import units as u
    from astropy.coordinates import SkyCoord

    c = SkyCoord(ra * u.rad, dec * u.rad, frame="icrs").transform_to(_ASTROPY_FRAMES[frame])
    sph = c.spherical
    return float(sph.lon.to_value(u.rad)), float(sph.lat.to_value(u.rad))


def make_test_ms(
    path: str | os.PathLike,
    *,
    n_antennas: int = 6,
    n_times: int = 10,
    n_channels: int | Sequence[int] = 4,
    pols: Sequence[str] = ("XX", "YY"),
    n_fields: int = 1,
    n_spws: int = 1,
    scans: int | Sequence[int] | None = None,
    weight_spectrum: bool = True,
    write_weight: bool = True,
    missing_baselines: int = 0,
    missing_rows: float = 0.0,
    flag_fraction: float = 0.05,
    flag_row_fraction: float = 0.02,
    datacolumns: Sequence[str] = ("DATA",),
    complex128: bool = False,
    autocorrelations: bool = False,
    telescope: str = "ALMA",
    phase_center: tuple[float, float] = DEFAULT_PHASE_CENTER,
    field_spacing_arcsec: float = 20.0,
    field_frame: str = "J2000",
    freq0: float = 230e9,
    spw_spacing: float = 2e9,
    channel_width: float = 1e8,
    integration_time: float = 6.0,
    start_time: float = 58849.0 * 86400.0,
    array_radius: float = 300.0,
    noise_jy: float = 1.0,
    sources: Sequence[tuple[float, float, float]] = (),
    seed: int = 0,
    rows_per_block: int | None = None,
) -> Path:
    """Write a small but realistic MeasurementSet with python-casacore.

    The main table is time-ordered (time, then spectral window, then baseline, as CASA writes
    it), its big columns use tiled storage managers with a fixed cell shape when every
    spectral window has the same number of channels, and UVW are computed from ITRF antenna
    positions for each field's phase center. Data are written block by block, so large MSs
    (for benchmarks) do not need their size in memory.

    Parameters
    ----------
    path
        Output ``.ms`` directory (must not exist).
    n_antennas, n_times
        Number of antennas; integrations per scan.
    n_channels
        Channels per spectral window (an int for all, or one per window).
    pols
        Correlation names, e.g. ``("XX", "YY")`` or ``("RR", "RL", "LR", "LL")``.
    n_fields, n_spws
        Number of fields (pointings ``field_spacing_arcsec`` apart in RA) and spectral windows
        (``spw_spacing`` Hz apart from ``freq0``). Every integration has all windows.
    scans
        Number of scans (default ``n_fields``; scan k observes field ``k % n_fields``), or an
        explicit field id per scan. Scans are numbered from 1, with a 60 s gap between them.
    weight_spectrum
        Write a WEIGHT_SPECTRUM column (per-channel weights that vary with channel).
    write_weight
        If False, WEIGHT (and WEIGHT_SPECTRUM) cells are left undefined, so readers must use
        SIGMA.
    missing_baselines
        Number of baselines absent from the whole MS.
    missing_rows
        Fraction of the remaining (time, baseline) rows left out at random.
    flag_fraction, flag_row_fraction
        Fraction of FLAG set at random; fraction of rows with FLAG_ROW set (FLAG itself is
        not set on those rows, so readers must honour FLAG_ROW).
    datacolumns
        Visibility columns to write: DATA and CORRECTED_DATA get independent noise on the
        sources, MODEL_DATA the noiseless sources.
    complex128
        Store visibilities as double-precision complex.
    field_frame
        Reference frame of FIELD directions (``J2000``, ``B1950`` or ``GALACTIC``); the
        fields are at the same sky positions whatever the frame.
    noise_jy
        Thermal noise per visibility (real and imaginary part), Jy. WEIGHT is 1/noise^2
        times a random factor between 0.5 and 2 per row (and per channel with
        WEIGHT_SPECTRUM).
    sources
        Point sources ``(ra_deg, dec_deg, flux_jy)`` (ICRS) added to every field with
        V = S exp(+2 pi i (u l + v m + w (n - 1)) / lambda) (docs/conventions.md).
    seed
        Random seed; the same arguments always give the same MS.
    rows_per_block
        Rows written per ``putcol`` (default: ~64 MB of visibilities).

    Returns
    -------
    pathlib.Path
        ``path``.
    """
    import casacore.tables as pt

    from xstack.io._mswrite import create_ms, write_subtables

    path = Path(path)
    if path.exists():
        raise FileExistsError(f"{path} exists")
    rng = np.random.default_rng(seed)
    telescope = str(telescope)
    lon, lat, height, dish = SITES.get(telescope.upper(), SITES["ALMA"])
    nchans = [int(n_channels)] * n_spws if np.ndim(n_channels) == 0 else [int(n) for n in n_channels]
    if len(nchans) != n_spws:
        raise ValueError("n_channels must be an int or have one entry per spectral window")
    pols = [str(p) for p in pols]
    npol = len(pols)
    if scans is None:
        scan_fields = [k % n_fields for k in range(n_fields)]
    elif np.ndim(scans) == 0:
        scan_fields = [k % n_fields for k in range(int(scans))]
    else:
        scan_fields = [int(f) for f in scans]

    # antennas: random east/north/up offsets around the site
    enu = np.column_stack([rng.normal(scale=array_radius / 2, size=(n_antennas, 2)),
                           rng.normal(scale=2.0, size=n_antennas)])
    positions = _geodetic_to_ecef(lon, lat, height) + enu @ _enu_to_ecef_rotation(lon, lat).T
    names = [f"{'DA' if telescope.upper() == 'ALMA' else 'ea'}{k + 1:02d}" for k in range(n_antennas)]

    a1_all, a2_all = np.triu_indices(n_antennas, k=0 if autocorrelations else 1)
    keep = np.ones(a1_all.size, dtype=bool)
    if missing_baselines:
        keep[rng.choice(a1_all.size, size=int(missing_baselines), replace=False)] = False
    a1_all, a2_all = a1_all[keep].astype(np.int32), a2_all[keep].astype(np.int32)
    nbl = a1_all.size

    # fields and spectral windows
    ra0, dec0 = phase_center
    fields = []
    for f in range(n_fields):
        ra = ra0 + np.deg2rad(f * field_spacing_arcsec / 3600.0) / np.cos(dec0)
        fields.append({"name": f"field{f}", "icrs": (ra, dec0),
                       "phase_center": _phase_dir_in_frame(ra, dec0, field_frame)})
    spws = []
    for s, nc in enumerate(nchans):
        f0 = freq0 + s * spw_spacing
        spws.append({"chan_freq": f0 + channel_width * np.arange(nc),
                     "chan_width": np.full(nc, channel_width), "name": f"spw{s}"})

    # row metadata: time-major, then spectral window, then baseline
    times, tfield, tscan = [], [], []
    t = float(start_time)
    for k, f in enumerate(scan_fields):
        for _ in range(n_times):
            times.append(t)
            tfield.append(f)
            tscan.append(k + 1)
            t += integration_time
        t += 60.0
    times = np.asarray(times)
    ntime = times.size
    t_idx = np.repeat(np.arange(ntime), n_spws * nbl)
    s_idx = np.tile(np.repeat(np.arange(n_spws), nbl), ntime)
    b_idx = np.tile(np.arange(nbl), ntime * n_spws)
    if missing_rows > 0:
        # drop whole (time, baseline) rows, in every spectral window
        drop_tb = rng.uniform(size=(ntime, nbl)) < missing_rows
        present = ~drop_tb[t_idx, b_idx]
        t_idx, s_idx, b_idx = t_idx[present], s_idx[present], b_idx[present]
    nrow = t_idx.size
    if nrow == 0:
        raise ValueError("no rows left to write")

    gha_t = _earth_rotation_angle(times)
    baseline_xyz = positions[a2_all] - positions[a1_all]

    complex_dtype = np.complex128 if complex128 else np.complex64
    cell_bytes = max(nchans) * npol * np.dtype(complex_dtype).itemsize
    block = int(rows_per_block or max(1, (64 * 1024**2) // cell_bytes))

    tab = create_ms(path, [(nc, npol) for nc in nchans], data_columns=tuple(datacolumns),
                    complex128=complex128, weight_spectrum=weight_spectrum,
                    fixed_weight=write_weight)
    try:
        tab.addrows(nrow)
        # scalar columns, all rows at once (small)
        fid = np.asarray(tfield)[t_idx].astype(np.int32)
        tab.putcol("TIME", times[t_idx])
        tab.putcol("TIME_CENTROID", times[t_idx])
        tab.putcol("INTERVAL", np.full(nrow, integration_time))
        tab.putcol("EXPOSURE", np.full(nrow, integration_time))
        tab.putcol("ANTENNA1", a1_all[b_idx])
        tab.putcol("ANTENNA2", a2_all[b_idx])
        tab.putcol("FIELD_ID", fid)
        tab.putcol("DATA_DESC_ID", s_idx.astype(np.int32))
        tab.putcol("SCAN_NUMBER", np.asarray(tscan)[t_idx].astype(np.int32))
        zeros = np.zeros(nrow, dtype=np.int32)
        for col in ("FEED1", "FEED2", "ARRAY_ID", "OBSERVATION_ID", "PROCESSOR_ID"):
            tab.putcol(col, zeros)
        tab.putcol("STATE_ID", np.full(nrow, -1, dtype=np.int32))
        flag_row = rng.uniform(size=nrow) < flag_row_fraction
        tab.putcol("FLAG_ROW", flag_row)
        uvw = np.empty((nrow, 3))
        for f in range(n_fields):
            sel = fid == f
            if sel.any():
                ra, dec = fields[f]["icrs"]
                uvw[sel] = uvw_from_itrf(baseline_xyz[b_idx[sel]], gha_t[t_idx[sel]] - ra, dec)
        tab.putcol("UVW", uvw)

        # big columns, in blocks of rows sharing one spectral window shape
        starts = [0]
        if len(set(nchans)) > 1:
            starts = [0, *np.flatnonzero(np.diff(s_idx) != 0) + 1]
        bounds = []
        for k, r0 in enumerate(starts):
            r1 = starts[k + 1] if k + 1 < len(starts) else nrow
            bounds.extend((b, min(b + block, r1)) for b in range(r0, r1, block))
        for r0, r1 in bounds:
            n = r1 - r0
            spw_rows = s_idx[r0:r1]
            nc = nchans[int(spw_rows[0])]
            if len(set(nchans)) == 1:
                freq = np.stack([spw["chan_freq"] for spw in spws])[spw_rows]
            else:  # a block holds one window only
                freq = np.broadcast_to(spws[int(spw_rows[0])]["chan_freq"], (n, nc))
            model = np.zeros((n, nc, npol), dtype=np.complex128)
            for ra_s, dec_s, flux in sources:
                for f in range(n_fields):
                    sel = fid[r0:r1] == f
                    if not sel.any():
                        continue
                    ra_c, dec_c = fields[f]["icrs"]
                    l, m, _, nm1 = radec_to_lmn(np.deg2rad(ra_s), np.deg2rad(dec_s), ra_c, dec_c)
                    uv = uvw[r0:r1][sel]
                    phase = 2 * np.pi * (uv[:, 0, None] * l + uv[:, 1, None] * m
                                         + uv[:, 2, None] * nm1) * freq[sel] / SPEED_OF_LIGHT
                    model[sel] += (flux * np.exp(1j * phase))[:, :, None]
            wfac = rng.uniform(0.5, 2.0, size=(n, npol))
            if weight_spectrum:
                wspec = (rng.uniform(0.5, 2.0, size=(n, nc, npol)) / noise_jy**2).astype(np.float32)
                weight = np.median(wspec, axis=1).astype(np.float32)
            else:
                wspec = None
                weight = (wfac / noise_jy**2).astype(np.float32)
            sigma = (1.0 / np.sqrt(weight)).astype(np.float32)
            for col in datacolumns:
                if col == "MODEL_DATA":
                    vis = model
                else:
                    noise = rng.standard_normal((n, nc, npol, 2)) * noise_jy
                    vis = model + noise[..., 0] + 1j * noise[..., 1]
                tab.putcol(col, vis.astype(complex_dtype), startrow=r0, nrow=n)
            tab.putcol("FLAG", rng.uniform(size=(n, nc, npol)) < flag_fraction, startrow=r0, nrow=n)
            if write_weight:
                tab.putcol("WEIGHT", weight, startrow=r0, nrow=n)
                if wspec is not None:
                    tab.putcol("WEIGHT_SPECTRUM", wspec, startrow=r0, nrow=n)
            tab.putcol("SIGMA", sigma, startrow=r0, nrow=n)
    finally:
        tab.close()

    write_subtables(
        path, antenna_names=names, antenna_positions=positions,
        dish_diameters=np.full(n_antennas, dish), telescope_name=telescope,
        fields=fields, spws=spws, pol_setups=[pols],
        data_descriptions=[(s, 0) for s in range(n_spws)],
        time_range=(float(times[0] - integration_time / 2), float(times[-1] + integration_time / 2)),
        history="xstack.testing.make_test_ms", stations=[f"PAD{k:03d}" for k in range(n_antennas)])
    if field_frame not in ("J2000", "ICRS"):
        with pt.table(os.path.join(path, "FIELD"), readonly=False, ack=False) as ftab:
            for col in ("PHASE_DIR", "DELAY_DIR", "REFERENCE_DIR"):
                kw = ftab.getcolkeywords(col)
                kw["MEASINFO"] = {"type": "direction", "Ref": field_frame}
                ftab.putcolkeywords(col, kw)
    return path
