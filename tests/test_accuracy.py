"""τ̂'s error against the truth delayed by the estimation delay
(hrp2_drake/estimation/accuracy.py): what the estimation and the balance experiments
judge."""

import numpy as np
import pytest

from hrp2_drake.estimation.accuracy import errors, shifted

PERIOD = 0.001  # s


def test_shifted_interpolates_a_fractional_delay():
    ramp = np.arange(10.0)[:, None]
    np.testing.assert_allclose(shifted(ramp, 1.5)[2:, 0], np.arange(8.0) + 0.5)
    assert np.all(np.isnan(shifted(ramp, 1.5)[:2]))
    np.testing.assert_allclose(shifted(ramp, 0.0), ramp)
    with pytest.raises(ValueError, match="a delay of -1 samples, expected >= 0"):
        shifted(ramp, -1)


def test_errors_find_an_estimate_delayed_by_k_samples():
    """An estimate that is the truth k samples late: no error at shift k, the
    delay's whole error at 0 (what the balance experiment reported before), and the
    peak of the delayed truth on the samples counted."""
    t = np.arange(2100) * PERIOD  # 2 s (whole periods) from start = 0.1 s
    true = np.column_stack([np.sin(2 * np.pi * t), 5.0 * np.cos(2 * np.pi * 3.0 * t)])
    k = 20
    estimate = shifted(true, k)  # τ̂(t) = τ(t − k·PERIOD)
    at_k = errors(t, estimate, true, k, start=0.1)
    np.testing.assert_array_equal(at_k["rms"], [0.0, 0.0])
    np.testing.assert_allclose(at_k["peak"], [1.0, 5.0], rtol=1e-4)
    np.testing.assert_array_equal(at_k["ratio"], [0.0, 0.0])
    at_0 = errors(t, estimate, true, 0, start=0.1)
    # sin(ωt) − sin(ω(t − d)): amplitude 2 sin(ωd/2), RMS that over √2.
    expected = [
        2 * np.sin(np.pi * f * k * PERIOD) / np.sqrt(2) * a
        for f, a in ((1.0, 1.0), (3.0, 5.0))
    ]
    np.testing.assert_allclose(at_0["rms"], expected, rtol=1e-3)
    assert np.all(at_0["ratio"] > 0.05)
    # The samples before the delayed truth exists are not counted.
    np.testing.assert_array_equal(errors(t, estimate, true, k, start=0.0)["rms"], 0.0)


def test_errors_name_a_window_with_no_sample():
    t = np.arange(10) * PERIOD
    with pytest.raises(ValueError, match="no sample from t = 1 s"):
        errors(t, np.zeros((10, 1)), np.zeros((10, 1)), 0, start=1.0)
