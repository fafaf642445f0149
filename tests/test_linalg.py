"""The plain-jnp Cholesky and triangular solves against numpy (float64), batched."""

import jax
import numpy as np
import pytest

from csf_jax import _linalg


def _spd(seed, batch, d):
    a = np.random.default_rng(seed).standard_normal((batch, d, d))
    return a @ np.swapaxes(a, -1, -2) + 0.1 * np.eye(d)


def test_cholesky_and_solves_match_numpy(x64):
    for d in (1, 3, 12, 25):
        a = _spd(d, 4, d)
        b = np.random.default_rng(d + 1).standard_normal((4, d))
        l = np.asarray(_linalg.cholesky(a))
        np.testing.assert_allclose(l, np.linalg.cholesky(a), rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(_linalg.solve_lower(l, b), np.linalg.solve(l, b[..., None])[..., 0],
                                   rtol=1e-9, atol=1e-11)
        lt = np.swapaxes(l, -1, -2)
        np.testing.assert_allclose(_linalg.solve_lower_transposed(l, b),
                                   np.linalg.solve(lt, b[..., None])[..., 0], rtol=1e-9, atol=1e-11)
        np.testing.assert_allclose(_linalg.cho_solve(l, b), np.linalg.solve(a, b[..., None])[..., 0],
                                   rtol=1e-8, atol=1e-10)


def test_cholesky_under_vmap_and_jit(x64):
    a = _spd(0, 6, 5)
    got = jax.jit(jax.vmap(_linalg.cholesky))(a)
    np.testing.assert_allclose(got, np.linalg.cholesky(a), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("d", [6, 23])
def test_broadcast_right_hand_sides(x64, d):
    """Candidates ``(K, N, d)`` against factors ``(N, d, d)``, and one ``(d,)`` against many."""
    a = _spd(3, 4, d)
    l = np.linalg.cholesky(a)
    z = np.random.default_rng(4).standard_normal((3, 4, d))
    want = np.linalg.solve(np.swapaxes(l, -1, -2)[None], z[..., None])[..., 0]
    np.testing.assert_allclose(_linalg.solve_lower_transposed(l, z), want, rtol=1e-9, atol=1e-11)
    b = z[0, 0]
    np.testing.assert_allclose(_linalg.cho_solve(l, b), np.linalg.solve(a, b), rtol=1e-8,
                               atol=1e-10)


def test_program_size_does_not_grow_with_d():
    """The factorisation and the solves are loops over columns: the same program for every d, so
    compile time is flat in d (unrolled, the solves would grow as d^2 operations)."""
    def size(d):
        a = np.eye(d, dtype=np.float32)[None]
        text = jax.jit(lambda a, b: _linalg.cho_solve(_linalg.cholesky(a), b)).lower(
            a, np.ones((1, d), np.float32)).as_text()
        return len([line for line in text.splitlines() if "=" in line])

    assert size(2) == size(20) == size(80)
