"""The CPU Gaussian rasteriser: closed form, a literal per-pixel reference, gradients vs finite
differences (float64), memory batching, and numerically hostile inputs."""
from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from sparseart.refine import render  # noqa: E402
from sparseart.refine.render import Camera, rasterize  # noqa: E402

D = torch.float64


def _camera(width=24, height=18, focal=20.0):
    K = np.array([[focal, 0.0, (width - 1) / 2], [0.0, focal, (height - 1) / 2], [0.0, 0.0, 1.0]])
    return Camera(K=K, world_to_cam=np.eye(4), width=width, height=height)


def _random_scene(n, seed, dtype=D):
    g = torch.Generator().manual_seed(seed)
    means = torch.cat([(torch.rand(n, 2, generator=g, dtype=dtype) - 0.5) * 0.8,
                       1.5 + torch.rand(n, 1, generator=g, dtype=dtype)], dim=1)
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    log_scales = math.log(0.06) + 0.4 * torch.randn(n, 3, generator=g, dtype=dtype)
    opacities = 0.3 + 0.5 * torch.rand(n, generator=g, dtype=dtype)
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    return means, quats, log_scales, opacities, colors


def test_isotropic_gaussian_footprint_matches_closed_form():
    camera = _camera(32, 24, focal=30.0)
    z, sigma, opacity = 2.0, 0.05, 0.7
    cx, cy = camera.K[0, 2], camera.K[1, 2]
    means = torch.tensor([[0.0, 0.0, z]], dtype=D)
    out = rasterize(means, torch.tensor([[1.0, 0, 0, 0]], dtype=D), torch.full((1, 3), math.log(sigma), dtype=D),
                    torch.tensor([opacity], dtype=D), torch.tensor([[1.0, 0.5, 0.0]], dtype=D), camera,
                    background=torch.tensor([0.0, 0.0, 1.0], dtype=D))
    var = (camera.K[0, 0] * sigma / z) ** 2 + render.LOW_PASS    # EWA + 0.3 px low-pass
    v, u = np.mgrid[0:24, 0:32]
    alpha = opacity * np.exp(-0.5 * ((u - cx) ** 2 + (v - cy) ** 2) / var)
    radius = math.ceil(3 * math.sqrt(var))
    inside = (np.abs(u - cx) <= radius) & (np.abs(v - cy) <= radius)
    alpha = np.where((alpha >= 1 / 255) & inside, np.minimum(alpha, 0.99), 0.0)
    np.testing.assert_allclose(out["alpha"].numpy(), alpha, atol=1e-12)
    np.testing.assert_allclose(out["depth"].numpy(), alpha * z, atol=1e-12)
    expected = alpha[..., None] * np.array([1.0, 0.5, 0.0]) + (1 - alpha[..., None]) * np.array([0, 0, 1.0])
    np.testing.assert_allclose(out["rgb"].numpy(), expected, atol=1e-12)


def _reference(means, quats, log_scales, opacities, colors, camera):
    """Literal port of the reference per-pixel loop (sorted front to back, both cut-offs)."""
    cov = render.covariance_3d(quats, log_scales)
    mean2d, conic, depth, radius, visible = (t.detach().numpy() for t in render.project(means, cov, camera))
    order = [i for i in np.argsort(depth, kind="stable") if visible[i]]
    image = np.zeros((camera.height, camera.width, 3))
    alpha_image = np.zeros((camera.height, camera.width))
    for row in range(camera.height):
        for col in range(camera.width):
            t = 1.0
            for i in order:
                if abs(col - mean2d[i, 0]) > radius[i] + 8 or abs(row - mean2d[i, 1]) > radius[i] + 8:
                    continue   # outside every tile the Gaussian was binned to (loose bound, alpha ~ 0 there)
                dx, dy = col - mean2d[i, 0], row - mean2d[i, 1]
                a, b, c = conic[i]
                power = min(0.0, -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy)
                alpha = min(0.99, float(opacities[i]) * math.exp(power))
                if alpha < 1 / 255:
                    continue
                if t * (1 - alpha) < 1e-4:
                    break
                image[row, col] += colors[i].numpy() * alpha * t
                t *= 1 - alpha
            alpha_image[row, col] = 1 - t
    return image, alpha_image


def test_matches_literal_reference_loop_including_cutoffs():
    means, quats, log_scales, opacities, colors = _random_scene(40, seed=1)
    opacities[:10] = 0.99   # saturate some pixels: exercises the 1e-4 transmittance stop
    camera = _camera()
    out = rasterize(means, quats, log_scales, opacities, colors, camera)
    image, alpha = _reference(means, quats, log_scales, opacities, colors, camera)
    # the rasteriser only draws a Gaussian in the tiles its 3-sigma box touches; the reference
    # loop uses a looser box, so allow the tiny alpha beyond 3 sigma
    np.testing.assert_allclose(out["alpha"].numpy(), alpha, atol=2e-3)
    np.testing.assert_allclose(out["rgb"].numpy(), image, atol=2e-3)


def test_batching_and_checkpointing_do_not_change_the_result():
    scene = [t.requires_grad_(True) for t in _random_scene(60, seed=2)]
    camera = _camera(40, 30)
    one = rasterize(*scene, camera, max_pairs=10 ** 9, checkpoint=False)
    many = rasterize(*scene, camera, max_pairs=2000, checkpoint=True)
    for key in ("rgb", "depth", "alpha"):
        torch.testing.assert_close(one[key], many[key], atol=1e-12, rtol=0)
    g_one = torch.autograd.grad(one["rgb"].sum() + one["depth"].sum(), scene)
    g_many = torch.autograd.grad(many["rgb"].sum() + many["depth"].sum(), scene)
    for a, b in zip(g_one, g_many):
        torch.testing.assert_close(a, b, atol=1e-10, rtol=1e-8)


def test_gradients_match_finite_differences_float64():
    means, quats, log_scales, opacities, colors = _random_scene(5, seed=3)
    opacity_logits = torch.logit(opacities)
    camera = _camera(16, 12, focal=14.0)
    weights = torch.rand(12, 16, 5, generator=torch.Generator().manual_seed(0), dtype=D)

    def loss(m, q, s, o, c):
        out = rasterize(m, q, s, torch.sigmoid(o), c, camera, background=torch.tensor([0.2, 0.3, 0.4], dtype=D))
        stacked = torch.cat([out["rgb"], out["depth"][..., None], out["alpha"][..., None]], dim=-1)
        return (stacked * weights).sum()

    inputs = tuple(t.clone().requires_grad_(True) for t in (means, quats, log_scales, opacity_logits, colors))
    assert torch.autograd.gradcheck(loss, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("case", ["stiff", "behind", "at_plane", "huge", "tiny", "zero_quat", "off_screen"])
def test_hostile_inputs_give_finite_images_and_gradients(case):
    means, quats, log_scales, opacities, colors = _random_scene(20, seed=4)
    if case == "stiff":
        log_scales[:, 0], log_scales[:, 1] = math.log(1e-7), math.log(0.5)
    elif case == "behind":
        means[:10, 2] = -1.0
    elif case == "at_plane":
        means[:10, 2] = 0.0
    elif case == "huge":
        log_scales[:5] = 80.0
    elif case == "tiny":
        log_scales[:] = -80.0
    elif case == "zero_quat":
        quats[:5] = 0.0
    elif case == "off_screen":
        means[:10, 0] = 50.0
    tensors = [t.clone().requires_grad_(True) for t in (means, quats, log_scales, opacities, colors)]
    out = rasterize(*tensors, _camera())
    for key in ("rgb", "depth", "alpha"):
        assert torch.isfinite(out[key]).all(), key
    (out["rgb"].sum() + out["depth"].sum() + out["alpha"].sum()).backward()
    for tensor in tensors:
        assert tensor.grad is None or torch.isfinite(tensor.grad).all()


def test_empty_and_invisible_scenes_render_the_background():
    camera = _camera()
    background = torch.tensor([0.1, 0.2, 0.3], dtype=D)
    empty = [torch.zeros(0, k, dtype=D) for k in (3, 4, 3)] + [torch.zeros(0, dtype=D), torch.zeros(0, 3, dtype=D)]
    out = rasterize(*empty, camera, background=background)
    assert torch.equal(out["rgb"], background.expand(18, 24, 3)) and out["alpha"].abs().sum() == 0
    means, quats, log_scales, opacities, colors = _random_scene(5, seed=5)
    means[:, 2] = -2.0
    out = rasterize(means, quats, log_scales, opacities, colors, camera, background=background)
    assert torch.allclose(out["rgb"], background.expand(18, 24, 3)) and float(out["alpha"].max()) == 0.0
    with pytest.raises(ValueError, match="camera size"):
        rasterize(means, quats, log_scales, opacities, colors, Camera(camera.K, np.eye(4), 0, 10))
