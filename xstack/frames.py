"""Spectral reference frames: which frame a partition's frequencies are in, and the Doppler
factor between two frames over an observation.

A MeasurementSet says the frame of its channel frequencies in SPECTRAL_WINDOW's
``MEAS_FREQ_REF`` (casacore's MFrequency types, :data:`MEAS_FREQ_REF`); an MSv4 store in the
``observer`` attribute of the partition's ``frequency`` coordinate, spelled as xradio writes it
(astropy frame names in lower case where casacore's frame has one: ``lsrk``, ``lsrd``,
``gcrs`` for GEO; casacore's own name in upper case otherwise: ``TOPO``, ``BARY``, ``REST``...,
:func:`msv4_observer`). xstack's stages name frames in upper case, casacore's way
(:func:`frequency_frame`); a store that does not say is TOPO (what every correlator writes,
and what xstack wrote before it recorded the frame).

Data taken in TOPO see a line at a fixed LSRK (or barycentric) frequency drift over a track:
the telescope's velocity along the line of sight changes with the Earth's rotation (<= 0.5
km/s) and orbit (<= 30 km/s). :func:`frame_ratio` gives, per integration, the factor r(t)
with nu_to = r(t) nu_from, exactly (relativistic Doppler of a moving observer) from astropy's
ephemerides:

* TOPO -> BARY: :meth:`astropy.coordinates.SkyCoord.radial_velocity_correction`
  (``kind="barycentric"``), the observer's barycentric velocity projected on the source
  direction, 1 + z_b = gamma (1 + beta . n); its gravitational-redshift term is taken out,
  because frequency frames (casacore's, astropy's ``SpectralCoord``) are kinematic;
* BARY -> LSRK / LSRD: the barycentre moves in the LSR frame with astropy's solar motion
  (:class:`astropy.coordinates.LSRK`: 20 km/s towards RA 270 deg, Dec +30 deg (B1900),
  Gordon 1975, the definition casacore's LSRK uses; :class:`astropy.coordinates.LSRD`:
  (U, V, W) = (9, 12, 7) km/s in Galactic coordinates, casacore's LSRD);
* nu_to = nu_from / (gamma (1 + beta . n)) for an observer moving with beta relative to the
  frame ``to``; factors between any two of TOPO, GEO, BARY, LSRK, LSRD are ratios of these.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from xstack.errors import OptionError
from xstack.spectral import SPEED_OF_LIGHT_KMS as _C_KMS

#: casacore's MFrequency types by ``MEAS_FREQ_REF`` code (SPECTRAL_WINDOW table).
MEAS_FREQ_REF: dict[int, str] = {0: "REST", 1: "LSRK", 2: "LSRD", 3: "BARY", 4: "GEO",
                                 5: "TOPO", 6: "GALACTO", 7: "LGROUP", 8: "CMB"}
_CODES = {name: code for code, name in MEAS_FREQ_REF.items()}

#: xradio's spelling of each casacore frame in ``frequency.attrs["observer"]``
#: (xradio ``_utils/schema.py``: LSRK -> lsrk, LSRD -> lsrd, GEO -> gcrs, the rest verbatim).
_MSV4_OBSERVER = {"LSRK": "lsrk", "LSRD": "lsrd", "GEO": "gcrs"}
#: astropy frame names an MSv4 writer may use, as casacore frames (``icrs``: at rest at the
#: solar-system barycentre, casacore's BARY).
_FROM_ASTROPY = {"lsrk": "LSRK", "lsrd": "LSRD", "gcrs": "GEO", "icrs": "BARY", "bary": "BARY",
                 "barycentric": "BARY", "topo": "TOPO", "topocentric": "TOPO"}

#: Frames :func:`frame_ratio` converts between.
DOPPLER_FRAMES = ("TOPO", "GEO", "BARY", "LSRK", "LSRD")


def frame_name(frame: Any) -> str:
    """A frame name (casacore's, xradio's or astropy's spelling; any case) as casacore's in
    upper case: ``"lsrk"`` -> ``"LSRK"``, ``"icrs"`` -> ``"BARY"``, ``"gcrs"`` -> ``"GEO"``.

    Raises
    ------
    OptionError
        A name that is no spectral frame.
    """
    text = str(frame).strip()
    if text.lower() in _FROM_ASTROPY:
        return _FROM_ASTROPY[text.lower()]
    if text.upper() in _CODES:
        return text.upper()
    raise OptionError(f"unknown spectral frame {frame!r} (known: "
                      f"{', '.join(_CODES)}; or astropy's lsrk, lsrd, icrs, gcrs)", option="frame")


def msv4_observer(frame: Any) -> str:
    """The ``observer`` attribute MSv4 (xradio) writes for ``frame``: ``"lsrk"``, ``"TOPO"``..."""
    try:
        name = frame_name(frame)
    except OptionError:
        return str(frame)  # another writer's frame name: kept as it is
    return _MSV4_OBSERVER.get(name, name)


def frame_from_meas_freq_ref(code: Any) -> str:
    """casacore's frame name of a SPECTRAL_WINDOW ``MEAS_FREQ_REF`` code (unknown: TOPO).

    Codes outside 0-8 (64 = "Undefined", or a table that has none) are taken as TOPO, what a
    correlator writes.
    """
    try:
        return MEAS_FREQ_REF.get(int(code), "TOPO")
    except (TypeError, ValueError):
        return "TOPO"


def meas_freq_ref(frame: Any) -> int:
    """The SPECTRAL_WINDOW ``MEAS_FREQ_REF`` code of a frame (``"LSRK"`` -> 1, ``"TOPO"`` -> 5)."""
    return _CODES[frame_name(frame)]


def frequency_frame(ds: Any) -> str:
    """The spectral frame of a partition's frequencies, upper case (``"TOPO"``, ``"LSRK"``...).

    Parameters
    ----------
    ds
        A partition (the internal view of :func:`xstack.schema.open_store`, or an MSv4
        ``VisibilityXds``); read from ``ds["frequency"].attrs["observer"]``.

    Returns
    -------
    str
        casacore's name of the frame; ``"TOPO"`` when the store does not say (stores written
        before xstack recorded the frame, data straight from a correlator).
    """
    attrs: Mapping[str, Any] = ds["frequency"].attrs if "frequency" in ds.coords else {}
    observer = attrs.get("observer")
    if observer is None or str(observer).strip() == "":
        return "TOPO"
    try:
        return frame_name(observer)
    except OptionError:
        # another writer's frame name xstack does not know: say it, in upper case
        return str(observer).strip().upper()


def _observer_factor(frame: str, times: Any, coord: Any, location: Any) -> np.ndarray:
    """gamma (1 + beta . n) of the telescope relative to ``frame`` per time: nu_topo =
    factor * nu_frame."""
    import astropy.units as u

    if frame == "TOPO":
        return np.ones(times.shape)
    if frame == "GEO":
        # the telescope's velocity relative to the geocentre (the Earth's rotation)
        _, vel = location.get_gcrs_posvel(times)
        return _moving(vel.xyz.to_value(u.km / u.s), coord)
    corr = coord.radial_velocity_correction(kind="barycentric", obstime=times, location=location)
    # astropy's correction includes the gravitational redshift at the telescope
    # (1 + z_b = gamma (1 + beta.n) / (1 + gr / c)); frequency frames are kinematic
    gr = location.gravitational_redshift(times)
    factor = ((1.0 + corr.to_value(u.km / u.s) / _C_KMS)
              * (1.0 + gr.to_value(u.km / u.s) / _C_KMS))
    if frame == "BARY":
        return factor
    from astropy.coordinates import ICRS, LSRD, LSRK

    # the barycentre's velocity in the LSR frame: a point at rest in ICRS, transformed
    zero_p, zero_v = 0.0 * u.km, 0.0 * u.km / u.s
    bary = ICRS(x=zero_p, y=zero_p, z=zero_p, v_x=zero_v, v_y=zero_v, v_z=zero_v,
                representation_type="cartesian", differential_type="cartesian")
    lsr = bary.transform_to(LSRK() if frame == "LSRK" else LSRD())
    v_sun = lsr.velocity.d_xyz.to_value(u.km / u.s)
    return factor * _moving(np.asarray(v_sun).reshape(3, *([1] * np.ndim(factor))), coord)


def _moving(v_kms: np.ndarray, coord: Any) -> np.ndarray:
    """gamma (1 + beta . n) of an observer moving with ICRS velocity ``v_kms`` (3, ...)."""
    n = coord.cartesian.xyz.value
    n = n / np.linalg.norm(n, axis=0)
    beta = np.asarray(v_kms) / _C_KMS
    b2 = np.sum(beta * beta, axis=0)
    return (1.0 + np.sum(beta * n, axis=0)) / np.sqrt(1.0 - b2)


def frame_ratio(time_s: Any, ra_deg: Any, dec_deg: Any, location_itrf_m: Any, *,
                to_frame: str, from_frame: str = "TOPO") -> np.ndarray:
    """Per time, the factor r(t) with nu_to = r(t) nu_from of a source at (ra, dec).

    Parameters
    ----------
    time_s
        Times in MJD seconds (UTC), as the ``time`` coordinate of a partition
        (:func:`xstack.schema.open_store`'s internal view).
    ra_deg, dec_deg
        ICRS direction of the source (scalars, or arrays broadcasting with ``time_s``), degrees.
    location_itrf_m
        The telescope's ITRF position (x, y, z) in metres: the array centre (a mean of the
        ``ANTENNA_POSITION``s; the antennas' spread changes r by < 1e-10).
    to_frame, from_frame
        Frame names, any spelling :func:`frame_name` accepts; converted between: TOPO, GEO,
        BARY, LSRK, LSRD.

    Returns
    -------
    numpy.ndarray
        float64, the broadcast shape of ``time_s``, ``ra_deg`` and ``dec_deg``; exactly 1.0
        everywhere when the two frames are the same.

    Raises
    ------
    OptionError
        A frame that is unknown or not converted (REST, GALACTO, LGROUP, CMB).
    """
    to, frm = frame_name(to_frame), frame_name(from_frame)
    for name in (to, frm):
        if name not in DOPPLER_FRAMES:
            raise OptionError(f"frequencies in frame {name} cannot be converted (only between "
                              f"{', '.join(DOPPLER_FRAMES)})", option="frame")
    t, ra, dec = np.broadcast_arrays(np.asarray(time_s, dtype=np.float64),
                                     np.asarray(ra_deg, dtype=np.float64),
                                     np.asarray(dec_deg, dtype=np.float64))
    if to == frm or t.size == 0:
        return np.ones(t.shape)
    import astropy.units as u
    from astropy.coordinates import EarthLocation, SkyCoord
    from astropy.time import Time

    # astropy's ephemerides cost ~ms per call: evaluate each distinct (time, direction) once
    keys = np.stack([t.ravel(), ra.ravel(), dec.ravel()], axis=1)
    uniq, inverse = np.unique(keys, axis=0, return_inverse=True)
    loc = np.asarray(location_itrf_m, dtype=np.float64).reshape(3)
    location = EarthLocation.from_geocentric(*loc, unit=u.m)
    times = Time(uniq[:, 0] / 86400.0, format="mjd", scale="utc")
    coord = SkyCoord(uniq[:, 1] * u.deg, uniq[:, 2] * u.deg, frame="icrs")
    # nu_topo = f_X nu_X for each frame X, so nu_to = (f_from / f_to) nu_from
    ratio = (_observer_factor(frm, times, coord, location)
             / _observer_factor(to, times, coord, location))
    return np.asarray(ratio, dtype=np.float64)[inverse.ravel()].reshape(t.shape)


def partition_frame_ratios(ds: Any, frame: str) -> np.ndarray:
    """Per integration of a partition, r(t) = nu_frame / nu_data.

    1 everywhere when the data are in ``frame`` already; TOPO data are converted towards
    the partition's phase centre for its array centre (the mean ``ANTENNA_POSITION``: the
    antennas' spread changes r by < 1e-10); across a primary beam the correction changes by
    < v_earth * theta (< 1e-6 of nu for a 0.5 degree field).

    Raises
    ------
    OptionError
        Data in a frame other than TOPO and ``frame`` (only TOPO data are converted).
    """
    have = frequency_frame(ds)
    want = frame_name(frame)
    times = np.asarray(ds["time"].values, dtype=np.float64)
    if have == want:
        return np.ones(times.size)
    if have != "TOPO":
        raise OptionError(f"the data's frequencies are in frame {have}, not {want}: only TOPO "
                          "data are converted", option="frame")
    ra0, dec0 = (float(x) for x in ds.attrs["phase_center"])
    location = np.asarray(ds["ANTENNA_POSITION"].values, dtype=np.float64).mean(axis=0)
    return frame_ratio(times, np.degrees(ra0), np.degrees(dec0), location, to_frame=want,
                       from_frame="TOPO")
