"""xstack.spectral: rest frequencies, observed line centres and the velocity convention,
against astropy's units and Doppler equivalencies (not against xstack's own arithmetic)."""

from __future__ import annotations

import astropy.units as u
import numpy as np
import pytest

from xstack.errors import OptionError
from xstack.spectral import (
    LINES,
    SPEED_OF_LIGHT_KMS,
    frequency_hz,
    observed_line_centre,
    rest_frequency,
    velocity_kms,
)


def test_speed_of_light_is_astropys():
    from astropy.constants import c

    assert SPEED_OF_LIGHT_KMS == c.to_value(u.km / u.s)


@pytest.mark.parametrize("text, expected_hz", [
    ("HI", 1420405751.768), ("hi", 1420405751.768), ("co (2-1)", 230.538e9),
    ("[cii]", 1900.5369e9), ("1420.405751786MHz", 1420405751.786), ("115.2712018 GHz", 115.2712018e9),
])
def test_rest_frequency_by_name_or_with_units(text, expected_hz):
    assert rest_frequency(text) == pytest.approx(expected_hz, rel=1e-15)


def test_rest_frequency_of_quantities_and_numbers():
    assert rest_frequency(1.4 * u.GHz) == pytest.approx(1.4e9, rel=1e-15)
    # a wavelength is converted by astropy's spectral equivalency
    assert rest_frequency(21.106114054 * u.cm) == pytest.approx(1420405751.8, rel=1e-9)
    assert rest_frequency(230.538e9) == 230.538e9


@pytest.mark.parametrize("bad", ["CO(9-8)x", "12 parsecs", -1.0, 0.0, float("nan"), 3 * u.m / u.s])
def test_bad_line_is_a_one_line_option_error(bad):
    with pytest.raises(OptionError) as err:
        rest_frequency(bad)
    assert "\n" not in str(err.value)


def test_hi_rest_frequency_matches_the_hyperfine_transition():
    # 1420.405751768 MHz (Hellwig et al. 1970), the value every HI survey uses
    assert LINES["HI"] == pytest.approx(1420.405751768e6, abs=1e-3)


def test_velocity_is_the_radio_convention_about_the_observed_centre():
    rest = LINES["CO(2-1)"]
    z = np.array([0.0, 0.5, 2.3])
    centre = observed_line_centre(rest, z)
    np.testing.assert_allclose(centre * (1 + z), rest, rtol=1e-15)
    rng = np.random.default_rng(1)
    for c_hz in centre:
        freq = c_hz * (1 + rng.uniform(-3e-3, 3e-3, 50))
        ours = velocity_kms(freq, c_hz)
        astropys = (freq * u.Hz).to_value(u.km / u.s, equivalencies=u.doppler_radio(c_hz * u.Hz))
        np.testing.assert_allclose(ours, astropys, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(frequency_hz(ours, c_hz), freq, rtol=1e-14)
    # lower frequency than the centre: positive velocity (receding)
    assert velocity_kms(0.999 * centre[0], centre[0]) > 0
