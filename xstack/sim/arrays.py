"""Antenna configurations (CASA ``.cfg`` files) and baseline geometry (uvw from time).

UVW follow the MeasurementSet convention that CASA writes: the baseline of a row is
``position(antenna1) - position(antenna2)``, projected on the ICRS/J2000 frame of the phase
center: u towards east, v towards north, w towards the source. (CASA's documents contradict
each other on the order; the real ALMA MeasurementSet written by CASA's importasdm that
pyuvdata ships, and pyuvdata's own reader, settle it: antenna1 - antenna2 for rows with
antenna1 < antenna2. ``tests/test_sim_arrays.py`` checks it against that MS.) The Earth's
orientation at each time comes from ERFA (IAU 2006/2000A precession-nutation and Earth
rotation, :func:`erfa.c2t06a`), with UT1 = UTC and no polar motion (the errors this leaves,
< 1 s of time and < 0.5 arcsec, only rotate the uv-coverage slightly: they do not change the
consistency between the stored uvw and the simulated phases). Checked against the real EVLA
MeasurementSet shipped with pyuvdata in ``tests/test_sim_arrays.py``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import erfa
import numpy as np

from xstack.errors import XstackError

#: Reference positions (ITRF, metres) of the observatories the packaged .cfg files use;
#: LOC (local east-north-up) coordinates are relative to these.
OBSERVATORIES: dict[str, tuple[float, float, float]] = {
    "ALMA": (2225142.18, -5440307.37, -2481029.85),
    "VLA": (-1601185.4, -5041977.5, 3554875.9),
    "EVLA": (-1601185.4, -5041977.5, 3554875.9),
    "WSRT": (3828630.63, 442449.11, 5064923.0),
    "MEERKAT": (5109360.13, 2006852.59, -3238948.13),
    "ATCA": (-4751640.18, 2791700.32, -3200490.62),
}

#: Packaged configurations: short name -> file under ``xstack/data/arrays``.
PACKAGED = {
    "vla.a": "vla.a.cfg", "vla.b": "vla.b.cfg", "vla.c": "vla.c.cfg", "vla.d": "vla.d.cfg",
    **{f"alma.cycle1.{i}": f"alma.cycle1.{i}.cfg" for i in range(1, 7)},
}

SECONDS_PER_DAY = 86400.0
SIDEREAL_RATE = 1.002737909350795  # sidereal seconds per UT1 second


@dataclass
class AntennaArray:
    """An interferometer: antenna names, ITRF positions (m), dish diameters (m)."""

    telescope: str
    names: list[str]
    positions: np.ndarray  # (nant, 3) ITRF metres
    diameters: np.ndarray  # (nant,) metres
    source: str = ""
    site: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @property
    def n_antennas(self) -> int:
        return len(self.names)

    def subset(self, selection: list[int] | list[str]) -> AntennaArray:
        """The array reduced to some antennas (by index or by name), in the order given."""
        idx = []
        for item in selection:
            if isinstance(item, str):
                if item not in self.names:
                    raise XstackError(f"array.antennas: no antenna named {item!r} in {self.source}")
                idx.append(self.names.index(item))
            else:
                if not 0 <= int(item) < self.n_antennas:
                    raise XstackError(f"array.antennas: index {item} out of range "
                                      f"(0..{self.n_antennas - 1})")
                idx.append(int(item))
        if len(set(idx)) != len(idx) or len(idx) < 2:
            raise XstackError("array.antennas: need at least 2 distinct antennas")
        return AntennaArray(self.telescope, [self.names[i] for i in idx], self.positions[idx],
                            self.diameters[idx], f"{self.source}[subset]", self.site)


def geodetic(xyz: Any) -> tuple[float, float, float]:
    """WGS84 (longitude, latitude, height) in (rad, rad, m) of an ITRF position."""
    lon, lat, h = erfa.gc2gd(1, np.asarray(xyz, dtype=np.float64))
    return float(lon), float(lat), float(h)


def enu_to_itrf(enu: np.ndarray, site: Any) -> np.ndarray:
    """Local east-north-up offsets (m) at ``site`` (ITRF m) to ITRF positions (m)."""
    lon, lat, _ = geodetic(site)
    sl, cl, sp, cp = math.sin(lon), math.cos(lon), math.sin(lat), math.cos(lat)
    # columns: unit vectors east, north, up in ITRF
    rot = np.array([[-sl, -sp * cl, cp * cl],
                    [cl, -sp * sl, cp * sl],
                    [0.0, cp, sp]])
    return np.asarray(site, dtype=np.float64)[None, :] + np.asarray(enu, np.float64) @ rot.T


def read_cfg(path: str | Path, telescope: str | None = None) -> AntennaArray:
    """Read a CASA simulator ``.cfg`` antenna file (coordsys XYZ or LOC).

    Lines starting with ``#`` are comments except ``# observatory=NAME`` and
    ``# coordsys=XYZ|LOC``; each other line is ``x y z diameter name``.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise XstackError(f"array: cannot read {path} ({exc.strerror})") from None
    observatory, coordsys = telescope, "XYZ"
    rows: list[tuple[float, float, float, float, str]] = []
    for lineno, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            body = s.lstrip("#").strip()
            if "=" in body:
                key, _, value = body.partition("=")
                key = key.strip().lower()
                if key == "observatory" and telescope is None:
                    observatory = value.split()[0].strip()
                elif key == "coordsys":
                    coordsys = value.split()[0].strip().upper()
            continue
        parts = s.split()
        try:
            x, y, z, d = (float(p) for p in parts[:4])
        except ValueError:
            raise XstackError(f"{path}:{lineno}: expected 'x y z diameter name'") from None
        name = parts[4] if len(parts) > 4 else f"A{len(rows):02d}"
        rows.append((x, y, z, d, name))
    if len(rows) < 2:
        raise XstackError(f"{path}: fewer than two antennas")
    if observatory is None:
        raise XstackError(f"{path}: no '# observatory=NAME' line (and no telescope given)")
    xyz = np.array([r[:3] for r in rows])
    diam = np.array([r[3] for r in rows])
    names = [r[4] for r in rows]
    site_key = observatory.upper()
    if coordsys.startswith("LOC"):
        if site_key not in OBSERVATORIES:
            raise XstackError(f"{path}: LOC coordinates need a known observatory "
                              f"({', '.join(OBSERVATORIES)}), got {observatory!r}")
        site = np.array(OBSERVATORIES[site_key])
        xyz = enu_to_itrf(xyz, site)
    elif coordsys.startswith("XYZ"):
        site = np.array(OBSERVATORIES.get(site_key, xyz.mean(axis=0)))
    else:
        raise XstackError(f"{path}: unknown coordsys {coordsys!r} (XYZ or LOC)")
    return AntennaArray(observatory, names, xyz, diam, str(path), site)


def packaged_array(name: str) -> AntennaArray:
    """One of the packaged configurations (``vla.a`` … ``vla.d``, ``alma.cycle1.1`` … ``.6``)."""
    key = name.lower().removesuffix(".cfg")
    if key not in PACKAGED:
        raise XstackError(f"array.config: unknown array {name!r} "
                          f"(known: {', '.join(PACKAGED)}, or a path to a .cfg file)")
    ref = resources.files("xstack").joinpath("data", "arrays", PACKAGED[key])
    with resources.as_file(ref) as path:
        return read_cfg(path)


# --------------------------------------------------------------------------- time & geometry

def _jd_pairs(mjd_seconds: np.ndarray) -> tuple[np.ndarray, ...]:
    """(tt1, tt2, ut1, ut2) two-part Julian dates for UTC MJD seconds (UT1 = UTC)."""
    mjd = np.asarray(mjd_seconds, dtype=np.float64) / SECONDS_PER_DAY
    day = np.floor(mjd)
    frac = mjd - day
    utc1 = 2400000.5 + day
    tai1, tai2 = erfa.utctai(utc1, frac)
    tt1, tt2 = erfa.taitt(tai1, tai2)
    return tt1, tt2, utc1, frac


def celestial_to_terrestrial(mjd_seconds: Any) -> np.ndarray:
    """(ntime, 3, 3) matrices rotating GCRS/ICRS vectors to ITRF at the given UTC times."""
    tt1, tt2, ut1, ut2 = _jd_pairs(np.atleast_1d(mjd_seconds))
    return erfa.c2t06a(tt1, tt2, ut1, ut2, 0.0, 0.0)


def uvw_basis(ra: float, dec: float) -> np.ndarray:
    """(3, 3) rows: unit vectors u (east), v (north), w (to the source) in ICRS."""
    sa, ca, sd, cd = math.sin(ra), math.cos(ra), math.sin(dec), math.cos(dec)
    return np.array([[-sa, ca, 0.0],
                     [-sd * ca, -sd * sa, cd],
                     [cd * ca, cd * sa, sd]])


def antenna_uvw(positions: np.ndarray, mjd_seconds: Any, ra: float, dec: float,
                reference: Any | None = None) -> np.ndarray:
    """Per-antenna (u, v, w) (ntime, nant, 3), metres, relative to ``reference`` (ITRF).

    Differences ``antenna_uvw[:, a1] - antenna_uvw[:, a2]`` are the MS UVW of the baselines.
    """
    pos = np.asarray(positions, dtype=np.float64)
    ref = pos.mean(axis=0) if reference is None else np.asarray(reference, np.float64)
    rel = pos - ref  # small numbers: no precision lost in the differences
    c2t = celestial_to_terrestrial(mjd_seconds)  # (nt, 3, 3)
    # ITRF -> ICRS is the transpose of c2t; then project onto (u, v, w)
    cel = np.einsum("tji,aj->tai", c2t, rel)
    return np.einsum("ki,tai->tak", uvw_basis(ra, dec), cel)


def baseline_uvw(positions: np.ndarray, antenna1: np.ndarray, antenna2: np.ndarray,
                 mjd_seconds: Any, ra: float, dec: float) -> np.ndarray:
    """MS UVW (ntime, nbaseline, 3) in metres: position(antenna1) - position(antenna2)."""
    ant = antenna_uvw(positions, mjd_seconds, ra, dec)
    return ant[:, antenna1, :] - ant[:, antenna2, :]


def greenwich_sidereal_angle(mjd_seconds: Any) -> np.ndarray:
    """Greenwich apparent sidereal time (rad) at UTC MJD seconds (UT1 = UTC)."""
    tt1, tt2, ut1, ut2 = _jd_pairs(np.atleast_1d(mjd_seconds))
    return erfa.gst06a(ut1, ut2, tt1, tt2)


def time_of_hour_angle(hour_angle: float, ra: float, longitude: float, date_mjd: float) -> float:
    """First UTC time (MJD seconds) on or after ``date_mjd`` (days) at which the local hour
    angle of right ascension ``ra`` equals ``hour_angle`` (all angles in radians)."""
    t = date_mjd * SECONDS_PER_DAY
    for _ in range(3):
        lst = float(greenwich_sidereal_angle(t)[0]) + longitude
        dha = (hour_angle - (lst - ra)) % (2 * math.pi)
        if abs(dha) < 1e-12 or abs(dha - 2 * math.pi) < 1e-12:
            break
        if dha > math.pi and t > date_mjd * SECONDS_PER_DAY:
            dha -= 2 * math.pi  # refining: go back rather than a day forward
        t += dha / (2 * math.pi) * SECONDS_PER_DAY / SIDEREAL_RATE
    return t


def antenna_elevations(positions: Any, mjd_seconds: Any, ra: float, dec: float) -> np.ndarray:
    """(ntime, nant) elevation (rad) of (ra, dec) at each antenna (ITRF m) at UTC times.

    The local vertical is each antenna's WGS84 normal (the geocentric direction differs by up
    to 0.19 deg, too much near an elevation limit); no refraction.
    """
    pos = np.atleast_2d(np.asarray(positions, dtype=np.float64))
    lon, lat, _ = erfa.gc2gd(1, pos)
    up = np.stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)], axis=-1)
    c2t = celestial_to_terrestrial(mjd_seconds)
    s_itrf = np.einsum("tij,j->ti", c2t, uvw_basis(ra, dec)[2])
    return np.arcsin(np.clip(s_itrf @ up.T, -1.0, 1.0))


def elevation(positions_site: Any, mjd_seconds: Any, ra: float, dec: float) -> np.ndarray:
    """Elevation (rad, shape (ntime,)) of (ra, dec) seen from one ITRF site at UTC times."""
    return antenna_elevations(positions_site, mjd_seconds, ra, dec)[:, 0]


def shadowed_antennas(ant_uvw: np.ndarray, diameters: np.ndarray) -> np.ndarray:
    """(ntime, nant) bool: antennas shadowed by another one at each time.

    Antenna i is shadowed when some antenna j lies in front of it (larger w, i.e. nearer the
    source) at a projected distance sqrt(du^2 + dv^2) smaller than (D_i + D_j) / 2.
    """
    d = np.asarray(diameters, dtype=np.float64)
    du = ant_uvw[:, None, :, 0] - ant_uvw[:, :, None, 0]  # [t, i, j] = u_j - u_i
    dv = ant_uvw[:, None, :, 1] - ant_uvw[:, :, None, 1]
    dw = ant_uvw[:, None, :, 2] - ant_uvw[:, :, None, 2]
    lim = 0.5 * (d[:, None] + d[None, :])
    hit = (np.hypot(du, dv) < lim[None]) & (dw > 0)
    n = d.size
    hit[:, np.arange(n), np.arange(n)] = False
    return hit.any(axis=2)
