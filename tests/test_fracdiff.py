import math

import numpy as np
import pytest

from lathed.analysis.fracdiff import GLDerivative, fracdiff, gl_weights


def test_weights_known_values():
    # w_j = w_{j-1} (1 - (p+1)/j): for p = 1/2: 1, -1/2, -1/8, -1/16, -5/128
    np.testing.assert_allclose(gl_weights(0.5, 4), [1, -0.5, -0.125, -0.0625, -5 / 128])
    np.testing.assert_allclose(gl_weights(1.0, 3), [1, -1, 0, 0])
    np.testing.assert_allclose(gl_weights(0.0, 3), [1, 0, 0, 0])
    # they are the binomial series of (1 - z)^p
    p = 0.3
    j = np.arange(6)
    binom = np.array([math.gamma(p + 1) / (math.gamma(k + 1) * math.gamma(p - k + 1)) for k in j])
    np.testing.assert_allclose(gl_weights(p, 5), (-1.0) ** j * binom, rtol=1e-12)


def test_half_derivative_of_t():
    # D^0.5 t = t^0.5 / Gamma(1.5) (Riemann-Liouville from 0); GL converges at O(h)
    h = 1e-4
    t = np.arange(0, 10001) * h
    d = fracdiff(t, 0.5, memory=len(t), h=h)
    exact = np.sqrt(t[-1]) / math.gamma(1.5)
    assert d[-1] == pytest.approx(exact, rel=2e-3)


def test_first_order_is_backward_difference():
    t = np.linspace(0, 1, 1001)
    x = np.sin(2 * np.pi * t)
    d = fracdiff(x, 1.0, memory=8, h=t[1] - t[0])
    np.testing.assert_allclose(d[10:], 2 * np.pi * np.cos(2 * np.pi * t[10:]), atol=0.05)


def test_streaming_equals_whole():
    rng = np.random.default_rng(0)
    x = rng.standard_normal(5000)
    whole = fracdiff(x, 0.7, memory=50, h=0.5)
    g = GLDerivative(0.7, 50, h=0.5)
    parts = np.concatenate([g(x[i:i + 333]) for i in range(0, len(x), 333)])
    np.testing.assert_allclose(parts, whole, rtol=1e-10, atol=1e-12)


def test_short_memory_error_within_podlubny_bound():
    # truncating the memory at L*h costs at most M (L h)^-p / |Gamma(1-p)| (short-memory principle)
    h, p = 1e-3, 0.5
    t = np.arange(0, 4000) * h
    x = np.sin(3 * t)
    full = fracdiff(x, p, memory=len(x), h=h)
    for mem in (500, 1000, 2000):
        short = fracdiff(x, p, memory=mem, h=h)
        err = np.max(np.abs(full[-100:] - short[-100:]))
        assert err <= 1.0 * (mem * h) ** (-p) / abs(math.gamma(1 - p))
    # for a constant the error is the dropped tail of the weights: shrinks with memory
    one = np.ones(4000)
    errs = [abs(fracdiff(one, p, len(one))[-1] - fracdiff(one, p, mem)[-1]) for mem in (100, 400, 1600)]
    assert errs[0] > errs[1] > errs[2] > 0


def test_bad_order():
    with pytest.raises(ValueError, match="fractional order"):
        gl_weights(-0.1, 3)
