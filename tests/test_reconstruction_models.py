"""Reconstruction networks, loss, HDR transform and fast inference."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_laplace

from kdtrace.config import DEFAULT_CONFIG
from reconstruction import hdr, speed
from reconstruction.inference import (
    DENOISER_HALO,
    SUPERRESOLUTION_HALO,
    denoise,
    make_runner,
    run_tiled,
    select_fast_inference,
    tile_grid,
)
from reconstruction.loss import (
    DENOISER_RANGE_FLOOR,
    DENOISER_SIGMA,
    EDGE_RANGE_FLOOR,
    MSE_WEIGHT,
    EdgeAwareLoss,
    InSpace,
    LaplacianOfGaussian,
    log_kernel,
    normalise_edges,
)
from reconstruction.models import (
    DEMODULATION_EPSILON,
    DEMODULATION_FLOOR,
    POOLING_MULTIPLE,
    Denoiser,
    Superresolution,
    bicubic_upsample,
    count_parameters,
    from_perceptual,
    remodulate,
    replicate_padded_conv,
    rgb_from_ycbcr,
    superresolve,
    to_perceptual,
    ycbcr_from_rgb,
)


def _randomise(layer: torch.nn.Conv2d) -> None:
    """Give an output layer random weights, so the tests see the whole net act on its input."""
    torch.nn.init.normal_(layer.weight, std=0.05)
    torch.nn.init.normal_(layer.bias, std=0.05)


@pytest.fixture(scope="module")
def denoiser() -> Denoiser:
    torch.manual_seed(0)
    model = Denoiser()
    _randomise(model.out)  # zero-initialised, i.e. the identity: tiling would pass trivially
    return model.eval()


@pytest.fixture(scope="module")
def sr_net() -> Superresolution:
    torch.manual_seed(1)
    model = Superresolution()
    _randomise(model.layers[-1])  # zero-initialised, i.e. exactly bicubic: tiling would pass trivially
    return model.eval()


def test_untrained_residual_denoiser_returns_its_noisy_input_and_the_direct_form_does_not():
    x = torch.rand(2, 6, 40, 24)
    with torch.inference_mode():
        assert torch.equal(Denoiser()(x), x[:, :3])
        direct = Denoiser(residual=False)(x)
    assert direct.shape == (2, 3, 40, 24) and not torch.allclose(direct, x[:, :3], atol=1e-3)
    assert count_parameters(Denoiser(residual=False)) == count_parameters(Denoiser()) == 95_107
    assert Denoiser(residual=False).config != Denoiser().config  # a checkpoint of one is refused by the other


def test_demodulated_denoiser_is_the_same_net_between_a_division_and_a_multiplication_by_the_albedo():
    torch.manual_seed(3)
    x = torch.rand(2, 6, 40, 24) * 3.0
    x[:, 3:] = torch.rand(2, 3, 40, 24)
    x[0, 3:, :5] = 0.0  # what has no albedo (sky, emitters, mirrors): not demodulated
    x[1, 3:, :5] = 0.03  # a dark diffuse surface: demodulated
    demodulated = Denoiser(demodulate=True)
    with torch.inference_mode():
        assert torch.allclose(demodulated(x), x[:, :3], atol=1e-5)  # untrained: the identity, as the paper net
        _randomise(demodulated.out)
        plain = Denoiser()
        plain.load_state_dict(demodulated.state_dict())  # same parameters, same names
        # the obvious reference: demodulate in linear radiance, run the plain net, remodulate
        scale = DEMODULATION_EPSILON + (1 - DEMODULATION_EPSILON) * x[:, 3:6]
        scale[0, :, :5] = 1.0
        inner = torch.cat([hdr.encode(hdr.decode(x[:, :3]) / scale), x[:, 3:]], dim=1)
        expected = hdr.decode(plain(inner)) * scale  # radiance (negative outputs decode to 0)
        assert torch.allclose(hdr.decode(demodulated(x)), expected, atol=1e-5, rtol=1e-5)
        assert not torch.allclose(hdr.decode(plain(x)), expected, atol=1e-3)
    assert count_parameters(demodulated) == 95_107
    assert 0.03 > DEMODULATION_FLOOR
    # a net whose outputs all turned negative (radiance 0) still learns: no clamp, a gradient everywhere
    dead = Denoiser(demodulate=True)
    torch.nn.init.constant_(dead.out.bias, -50.0)
    target = torch.full((2, 3, 40, 24), 0.5)
    loss = torch.nn.functional.mse_loss(dead(x), target)
    assert torch.equal(hdr.decode(dead(x).detach()), torch.zeros_like(target))
    loss.backward()
    assert dead.out.bias.grad is not None and bool((dead.out.bias.grad < 0).all())
    assert demodulated.config != Denoiser().config  # a checkpoint of one is refused by the other
    assert "demodulate" not in Denoiser().config["kwargs"]  # the paper net's cache keys are unchanged


def test_perceptual_denoiser_is_the_same_net_on_log1p_of_exposed_radiance():
    torch.manual_seed(4)
    x = torch.rand(2, 6, 40, 24)
    x[:, :3] = hdr.encode(torch.rand(2, 3, 40, 24) ** 4 * 0.02)  # dark radiance, as Crytek Sponza's
    perceptual = Denoiser(perceptual=64.0)
    gain = perceptual.calibrate(x[:, :3])
    radiance = hdr.decode(x[:, :3]).permute(0, 2, 3, 1).reshape(-1, 3).double()
    white = torch.quantile(radiance @ torch.tensor([0.2126, 0.7152, 0.0722], dtype=torch.float64), 0.99)
    assert gain == pytest.approx(64.0 / float(white), rel=1e-4)  # G times the display exposure
    with torch.inference_mode():
        assert torch.allclose(perceptual(x), x[:, :3], atol=1e-5)  # untrained: the identity
        _randomise(perceptual.out)
        plain = Denoiser()
        plain.load_state_dict({k: v for k, v in perceptual.state_dict().items() if k != "radiance_gain"})
        # the obvious reference in float64: w = log1p(g·x)/log1p(G), the plain net on w, then back
        transfer = np.log1p(64.0)
        inner = torch.cat([torch.log1p(gain * hdr.decode(x[:, :3].double())).float() / transfer, x[:, 3:]], dim=1)
        expected = torch.expm1(plain(inner).double().clamp_min(0) * transfer) / gain
        # float32 inside the net against float64 around it
        assert torch.allclose(hdr.decode(perceptual(x).double()), expected, rtol=3e-3, atol=1e-7)
        assert not torch.allclose(hdr.decode(plain(x).double()), expected, rtol=0.1)
    restored = Denoiser(**perceptual.config["kwargs"])
    restored.load_state_dict(perceptual.state_dict())  # the calibrated gain travels with the weights
    assert float(restored.radiance_gain) == pytest.approx(gain, rel=1e-6)
    assert count_parameters(perceptual) == 95_107
    assert perceptual.config != Denoiser().config and "perceptual" not in Denoiser().config["kwargs"]
    with pytest.raises(ValueError, match="separate variants"):
        Denoiser(demodulate=True, perceptual=64.0)
    with pytest.raises(ValueError, match="positive finite"):
        Denoiser(perceptual=-1.0)
    with pytest.raises(ValueError, match="only a perceptual"):
        Denoiser().calibrate(x[:, :3])
    with pytest.raises(ValueError, match="no exposure"):
        Denoiser(perceptual=64.0).calibrate(torch.zeros(1, 3, 8, 8))
    # the loss is taken in the transfer: a dark error the log1p space barely sees weighs as much as a bright one
    loss = InSpace(torch.nn.functional.mse_loss, lambda z: to_perceptual(z, perceptual.radiance_gain, 64.0), "w")
    dark, bright = torch.full((1, 3, 4, 4), 1e-3), torch.full((1, 3, 4, 4), 1e-1)
    in_log1p = [float(torch.nn.functional.mse_loss(hdr.encode(v * 1.5), hdr.encode(v))) for v in (dark, bright)]
    in_transfer = [float(loss(hdr.encode(v * 1.5), hdr.encode(v))) for v in (dark, bright)]
    assert in_log1p[1] / in_log1p[0] > 1000 and in_transfer[1] / in_transfer[0] < 10
    assert loss.config == {"loss": "function", "space": "w"}


def test_perceptual_transfer_round_trips_and_is_finite_with_a_gradient_everywhere():
    encoded = torch.tensor([-1e4, -3.0, 0.0, 1e-4, 0.5, 3.0, 20.0, 1e4], requires_grad=True)
    for gain in (1e-3, 1.0, 1e4):
        gain = torch.tensor(gain)
        forward = to_perceptual(encoded, gain, 64.0)
        back = from_perceptual(forward, gain, 64.0)
        assert bool(torch.isfinite(forward).all()) and torch.allclose(back, encoded, rtol=1e-5, atol=1e-5)
        encoded.grad = None
        back.sum().backward()
        assert bool(torch.isfinite(encoded.grad).all()) and bool((encoded.grad > 0).all())


def test_remodulate_is_the_multiplication_in_linear_radiance_and_finite_with_a_gradient_everywhere():
    encoded = torch.tensor([0.0, 1e-4, 0.5, 3.0, 20.0], dtype=torch.float64)
    scale = torch.tensor([0.01, 0.3, 1.0], dtype=torch.float64)[:, None]
    # the obvious formula, exact in float64 at these values
    assert torch.allclose(remodulate(encoded, scale), torch.log1p(torch.expm1(encoded) * scale), rtol=1e-12, atol=1e-15)
    extreme = torch.tensor([-1e4, -50.0, -1e-3, 100.0, 1e4], requires_grad=True)  # float32: expm1 overflows at 89
    out = remodulate(extreme, torch.tensor([[0.01], [1.0]]))
    out.sum().backward()
    assert bool(torch.isfinite(out).all()) and bool((extreme.grad > 0).all())
    assert bool((out[:, :3] < 0).all())  # negative radiance stays negative (decode clamps it to 0)


def test_parameter_counts_match_the_paper():
    assert count_parameters(Denoiser()) == 95_107
    assert count_parameters(Denoiser(("albedo", "normal", "depth"))) == 96_259
    assert count_parameters(Superresolution()) == 37_793


def test_denoiser_rejects_bad_configuration_and_input(denoiser):
    with pytest.raises(ValueError, match="albedo"):
        Denoiser(("normal",))
    with pytest.raises(ValueError, match="ordered subset"):
        Denoiser(("albedo", "depth", "normal"))
    with pytest.raises(ValueError, match=r"\(N, 6, H, W\)"):
        denoiser(torch.zeros(1, 3, 16, 16))
    with pytest.raises(ValueError, match=r"\(N, 1, H, W\)"):
        Superresolution()(torch.zeros(1, 3, 16, 16))


@pytest.mark.parametrize("size", [(1, 1), (33, 17), (47, 65)])
def test_any_size_keeps_its_size(denoiser, sr_net, size):
    with torch.inference_mode():
        assert denoiser(torch.rand(2, 6, *size)).shape == (2, 3, *size)
        assert Denoiser(("albedo", "normal", "depth")).eval()(torch.rand(1, 10, *size)).shape == (1, 3, *size)
        assert sr_net(torch.rand(1, 1, *size)).shape == (1, 1, *size)


def test_denoiser_pads_bottom_right_by_replication(denoiser):
    x = torch.rand(1, 6, 50, 70)
    padded = torch.nn.functional.pad(x, (0, 96 - 70, 0, 64 - 50), mode="replicate")
    with torch.inference_mode():
        torch.testing.assert_close(denoiser(x), denoiser(padded)[..., :50, :70], rtol=0, atol=1e-6)


def test_ycbcr_round_trip_and_bt601_values():
    rgb = np.random.default_rng(0).random((9, 7, 3))
    np.testing.assert_allclose(rgb_from_ycbcr(ycbcr_from_rgb(rgb)), rgb, atol=1e-12)
    white = ycbcr_from_rgb(np.ones((1, 1, 3)))[0, 0]
    np.testing.assert_allclose(white, [1.0, 0.5, 0.5], atol=1e-6)
    np.testing.assert_allclose(ycbcr_from_rgb(np.array([1.0, 0.0, 0.0]))[0], 0.299)
    tensor = torch.from_numpy(rgb).permute(2, 0, 1)[None]
    np.testing.assert_allclose(ycbcr_from_rgb(tensor, channel_axis=-3)[0].permute(1, 2, 0).numpy(), ycbcr_from_rgb(rgb))
    with pytest.raises(ValueError, match="3 channels"):
        ycbcr_from_rgb(np.zeros((4, 4, 2)))


def test_superresolve_doubles_size_and_keeps_chroma(sr_net):
    low = np.random.default_rng(2).random((13, 10, 3)).astype(np.float32)
    high = superresolve(sr_net, low)
    assert high.shape == (26, 20, 3) and high.dtype == np.float32
    assert high.min() >= 0.0 and high.max() <= 1.0
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        superresolve(sr_net, low[:, :, :2])
    with pytest.raises(ValueError, match="NaN"):
        superresolve(sr_net, np.full((4, 4, 3), np.nan))


def test_superresolve_is_the_ycbcr_round_trip_with_the_refined_luma(sr_net):
    """Bicubic RGB plus the change of Y equals replacing Y in YCbCr and converting back."""
    low = np.random.default_rng(5).random((21, 17, 3)).astype(np.float32)
    with torch.inference_mode():
        ycbcr = ycbcr_from_rgb(bicubic_upsample(torch.from_numpy(low).permute(2, 0, 1)[None]).clamp(0.0, 1.0),
                               channel_axis=-3)
        y = sr_net(ycbcr[:, :1])
        round_trip = rgb_from_ycbcr(torch.cat([y, ycbcr[:, 1:]], dim=1), channel_axis=-3).clamp(0.0, 1.0)
    np.testing.assert_allclose(superresolve(sr_net, low), round_trip[0].permute(1, 2, 0).numpy(), rtol=0, atol=2e-6)
    assert float((y - ycbcr[:, :1]).abs().max()) > 1e-3  # a net that acts


@pytest.mark.parametrize("sigma", [1.4, 1.0])
def test_log_matches_scipy(sigma):
    image = np.random.default_rng(3).random((2, 40, 37))
    log = LaplacianOfGaussian(sigma)
    ours = log(torch.from_numpy(image)[None])[0].numpy()
    single = log(torch.from_numpy(image).float()[None])[0].numpy()
    for channel in range(2):
        expected = gaussian_laplace(image[channel], sigma, mode="nearest")
        np.testing.assert_allclose(ours[channel], expected, rtol=0, atol=1e-12)
        np.testing.assert_allclose(single[channel], expected, rtol=0, atol=1e-6)


@pytest.mark.parametrize("dtype, tolerance", [(torch.float64, 1e-12), (torch.float32, 2e-6)])
@pytest.mark.parametrize("size", [(29, 41), (4, 3), (128, 128)])
def test_log_as_matrix_products_is_the_direct_convolution_and_so_is_its_gradient(dtype, tolerance, size):
    """The slow reference: one 2-D convolution with :func:`log_kernel` on the replicate-padded image."""
    kernel = torch.from_numpy(log_kernel(DENOISER_SIGMA))[None, None].to(dtype)
    radius = kernel.shape[-1] // 2

    def direct(x):
        n, c, h, w = x.shape
        padded = torch.nn.functional.pad(x.reshape(n * c, 1, h, w), (radius,) * 4, mode="replicate")
        return torch.nn.functional.conv2d(padded, kernel).reshape(n, c, h, w)

    generator = torch.Generator().manual_seed(size[0])
    x = torch.rand(3, 2, *size, dtype=dtype, generator=generator, requires_grad=True)
    weights = torch.rand(3, 2, *size, dtype=dtype, generator=generator)
    log = LaplacianOfGaussian(DENOISER_SIGMA)
    ours, reference = log(x), direct(x)
    torch.testing.assert_close(ours, reference, rtol=0, atol=tolerance)
    (ours_gradient,) = torch.autograd.grad((ours * weights).sum(), x)
    (reference_gradient,) = torch.autograd.grad((reference * weights).sum(), x)
    torch.testing.assert_close(ours_gradient, reference_gradient, rtol=0, atol=tolerance * 10)
    assert float(reference.detach().abs().max()) > 0.1  # a response to compare


def test_edge_maps_are_normalised_and_safe_on_constant_images():
    log = LaplacianOfGaussian(1.4)
    edges = normalise_edges(log(torch.rand(2, 3, 32, 32)))
    assert edges.min() == 0.0 and torch.allclose(edges.amax(dim=(-2, -1)), torch.ones(2, 3))
    constant = torch.full((1, 3, 16, 16), 0.7, requires_grad=True)
    loss = EdgeAwareLoss(1.4)(constant, torch.full((1, 3, 16, 16), 0.7))
    loss.backward()
    assert loss.item() == pytest.approx(0.0, abs=1e-10)
    assert torch.isfinite(constant.grad).all()


def test_edge_range_floor_bounds_how_much_a_flat_target_amplifies_the_noise_left_in_a_prediction():
    torch.manual_seed(5)
    target = torch.full((1, 3, 32, 32), 0.004)  # a flat, dark crop (half of Sponza's have a LoG range < 0.005)
    prediction = target + 0.002 * torch.randn_like(target)
    log = LaplacianOfGaussian(DENOISER_SIGMA)
    edge_mse = torch.mean((log(prediction) - log(target)) ** 2)
    for floor in (EDGE_RANGE_FLOOR, DENOISER_RANGE_FLOOR):
        loss = EdgeAwareLoss(DENOISER_SIGMA, floor)
        assert loss(prediction, target).item() == pytest.approx(
            MSE_WEIGHT * torch.mean((prediction - target) ** 2).item() + (1 - MSE_WEIGHT) * edge_mse.item() / floor**2,
            rel=1e-4)
        assert loss.config["range_floor"] == floor  # another floor is another model's cache key
    # the profiles that train at scale use the documented value; quick keeps its baselines' one
    floors = {name: DEFAULT_CONFIG.reconstruction.profile(name).denoiser_edge_range_floor
              for name in ("quick", "standard", "paper")}
    assert floors == {"quick": EDGE_RANGE_FLOOR, "standard": DENOISER_RANGE_FLOOR, "paper": DENOISER_RANGE_FLOOR}


def test_loss_weights_and_gradient():
    torch.manual_seed(4)
    target = torch.rand(2, 3, 24, 24)
    prediction = (target + 0.1 * torch.randn_like(target)).requires_grad_()
    loss_fn = EdgeAwareLoss(1.0)
    loss = loss_fn(prediction, target)
    mse = torch.mean((prediction - target) ** 2)
    log_p, log_t = (torch.from_numpy(np.stack([[gaussian_laplace(c, 1.0, mode="nearest") for c in image]
                                                for image in x.detach().numpy().astype(np.float64)])).float()
                    for x in (prediction, target))
    low, high = log_t.amin(dim=(-2, -1), keepdim=True), log_t.amax(dim=(-2, -1), keepdim=True)
    edge = torch.mean(((log_p - low) / (high - low) - (log_t - low) / (high - low)) ** 2)  # target's range for both
    assert loss.item() == pytest.approx((0.7 * mse + 0.3 * edge).item(), rel=1e-4)
    # a contrast error is an edge error too (independently normalised maps would be identical)
    doubled_edge_term = loss_fn(2 * target, target) - 0.7 * torch.mean(target**2)
    assert doubled_edge_term.item() > 0.3 * 0.01
    loss.backward()
    assert torch.isfinite(prediction.grad).all() and prediction.grad.abs().sum() > 0
    assert loss_fn(target, target).item() == 0.0
    with pytest.raises(ValueError, match="shape"):
        loss_fn(target, target[:, :2])


def test_hdr_round_trip_and_bad_input():
    radiance = np.array([0.0, 1e-4, 0.5, 1.0, 37.0, 1e4], dtype=np.float32)
    np.testing.assert_allclose(hdr.decode(hdr.encode(radiance)), radiance, rtol=1e-6)
    tensor = torch.from_numpy(radiance)
    torch.testing.assert_close(hdr.decode(hdr.encode(tensor)), tensor, rtol=1e-6, atol=0)
    assert hdr.encode(np.array([-0.1]))[0] == 0.0
    assert hdr.decode(np.array([-2.0]))[0] == 0.0
    bad = np.array([1.0, np.nan, np.inf, -np.inf, -3.0])
    with pytest.raises(ValueError, match="3 NaN/inf"):
        hdr.encode(bad)
    clean, replaced = hdr.sanitize(bad)
    assert replaced == {"nonfinite": 3, "negative": 1}
    np.testing.assert_array_equal(clean, [1.0, 0, 0, 0, 0])
    clean_t, replaced_t = hdr.sanitize(torch.from_numpy(bad))
    assert replaced_t == replaced and torch.equal(clean_t, torch.from_numpy(clean))


def test_denoiser_input_stacking_and_errors():
    rng = np.random.default_rng(5)
    color, albedo = rng.random((8, 9, 3)) * 4, rng.random((8, 9, 3))
    x = hdr.denoiser_input(color, albedo)
    assert x.shape == (6, 8, 9) and x.dtype == torch.float32
    np.testing.assert_allclose(x[:3].permute(1, 2, 0).numpy(), np.log1p(color), rtol=1e-6)
    normal, depth = rng.random((8, 9, 3)) * 2 - 1, rng.random((8, 9)) * 10
    assert hdr.denoiser_input(color, albedo, normal, depth).shape == (10, 8, 9)
    with pytest.raises(ValueError, match="albedo must have"):
        hdr.denoiser_input(color, albedo[:4])
    with pytest.raises(ValueError, match="together"):
        hdr.denoiser_input(color, albedo, normal)
    with pytest.raises(ValueError, match=r"albedo must lie in \[0.0, 1.0\]"):
        hdr.denoiser_input(color, albedo + 2)
    color[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN/inf"):
        hdr.denoiser_input(color, albedo)


def test_tile_grid_covers_the_frame_once():
    cores = tile_grid(96, 160, 50, 32)
    coverage = np.zeros((96, 160), dtype=int)
    for y0, y1, x0, x1 in cores:
        assert y0 % 32 == 0 and x0 % 32 == 0
        coverage[y0:y1, x0:x1] += 1
    assert (coverage == 1).all()


def test_tiled_denoiser_matches_whole_frame(denoiser):
    torch.manual_seed(6)
    x = torch.rand(1, 6, 150, 201)
    with torch.inference_mode():
        whole = denoiser(x)
    tiled = run_tiled(denoiser, x, tile=32, halo=DENOISER_HALO, align=POOLING_MULTIPLE, workers=2)
    assert tiled.shape == whole.shape
    assert (tiled - whole).abs().max().item() < 1e-5
    # a halo below the contamination depth visibly breaks the match
    short = run_tiled(denoiser, x, tile=32, halo=DENOISER_HALO - 32, align=POOLING_MULTIPLE, workers=1)
    assert (short - whole).abs().max().item() > 1e-6
    with pytest.raises(ValueError, match="multiple"):
        run_tiled(denoiser, x, tile=32, halo=40, align=POOLING_MULTIPLE)


def test_tiled_superresolution_matches_whole_frame(sr_net):
    y = torch.rand(1, 1, 70, 53)
    with torch.inference_mode():
        whole = sr_net(y)
    tiled = run_tiled(sr_net, y, tile=20, halo=SUPERRESOLUTION_HALO, workers=2)
    assert (tiled - whole).abs().max().item() < 1e-5


def test_denoise_end_to_end_tiled_equals_whole(denoiser):
    rng = np.random.default_rng(7)
    color, albedo = (rng.random((64, 80, 3)) * 3).astype(np.float32), rng.random((64, 80, 3)).astype(np.float32)
    whole = denoise(denoiser, color, albedo)
    tiled = denoise(denoiser, color, albedo, tile=32, workers=2)
    assert whole.shape == (64, 80, 3) and whole.dtype == np.float32 and (whole >= 0).all()
    assert np.abs(tiled - whole).max() < 1e-4
    with pytest.raises(ValueError, match="10 input channels"):
        denoise(Denoiser(("albedo", "normal", "depth")), color, albedo)


def test_fast_inference_decision_respects_the_psnr_limit(denoiser):
    torch.manual_seed(8)
    x = torch.rand(1, 6, 64, 64)
    reference = np.random.default_rng(8).random((64, 64, 3))
    decision = select_fast_inference(denoiser, x, reference, decode=hdr.decode, repeats=2)
    by_option = {result.option: result for result in decision.results}
    assert by_option["fp32"].speedup == 1.0 and not by_option["fp32"].accepted
    for result in decision.results:
        assert result.accepted == (
            result.option != "fp32" and abs(result.psnr_change) <= 0.05 and result.speedup >= 1.05
        )
        assert result.max_abs_difference < 0.05
    assert by_option["channels_last"].max_abs_difference < 1e-5
    assert by_option["jit_freeze"].max_abs_difference < 1e-5
    chosen = next(r for r in decision.results if r.option == decision.chosen)
    assert decision.chosen == "fp32" or chosen.accepted
    strict = select_fast_inference(denoiser, x, reference, decode=hdr.decode, repeats=1, min_speedup=1e9)
    assert strict.chosen == "fp32"
    with pytest.raises(ValueError, match="unknown option"):
        make_runner(denoiser, "fp8")


@pytest.mark.parametrize("kernel", [3, 5, 9])
@pytest.mark.parametrize("size", [(1, 1), (8, 8), (9, 40), (37, 23), (64, 64)])
def test_replicate_padded_conv_is_the_padded_convolution(kernel, size):
    """Border strips convolved apart: the same outputs as padding the whole input, small frames included."""
    torch.manual_seed(kernel)
    conv = torch.nn.Conv2d(4, 3, kernel, padding=kernel // 2, padding_mode="replicate")
    x = torch.rand(2, 4, *size) * 4 - 2  # a border unlike its inside: zero padding would differ there
    with torch.inference_mode():
        expected, got = conv(x), replicate_padded_conv(x, conv)
    assert got.shape == expected.shape == (2, 3, *size)
    torch.testing.assert_close(got, expected, rtol=0, atol=1e-5)
    zero_padded = torch.nn.functional.conv2d(x, conv.weight, conv.bias, padding=kernel // 2)
    if min(size) > 1:
        assert (zero_padded - expected).abs().max() > 1e-3  # the strips were needed


def test_superresolution_without_gradients_equals_training_forward(sr_net):
    y = torch.rand(1, 1, 45, 38)
    with torch.no_grad():
        inference = sr_net(y)
    with torch.enable_grad():
        training = sr_net(y)
    torch.testing.assert_close(inference, training.detach(), rtol=0, atol=1e-5)


@pytest.mark.skipif(not (torch.cpu._is_avx512_bf16_supported() or torch.cpu._is_amx_tile_supported()),
                    reason="bf16 runners need AVX512-BF16 or AMX")
@pytest.mark.parametrize("option", ["bf16", "channels_last_bf16"])
def test_bf16_superresolution_runner_converts_a_copy_and_keeps_the_residual_in_fp32(sr_net, option):
    """bf16 weights once instead of autocast per call: the autocast result, and the caller's net untouched."""
    y = torch.rand(1, 1, 70, 90)
    run = make_runner(sr_net, option)
    got = run(y)
    assert all(p.dtype == torch.float32 for p in sr_net.parameters())
    with torch.inference_mode(), torch.autocast("cpu", dtype=torch.bfloat16):
        x = y
        for layer in sr_net.layers[:-1]:
            x = torch.relu(layer(x))
        autocast = y + sr_net.layers[-1](x).float()
    assert got.dtype == torch.float32
    # One bf16 rounding of the correction apart at most; the input itself is carried in fp32.
    correction = (autocast - y).abs().max()
    assert (got - autocast).abs().max() <= 2 ** -7 * correction + 1e-6
    assert (got - y).abs().max() > 0.01 * correction  # the net acted


def test_superresolution_arithmetic_and_its_floor_on_this_machine(sr_net):
    """The §5.1 net costs 2 FLOP per weight and output pixel: 79 GFLOP for a 1024x1024 frame."""
    weights = sum(layer.weight.numel() for layer in sr_net.layers)
    assert weights == 37_696  # 37,793 parameters minus 97 biases
    assert speed.full_resolution_gflop(sr_net, 1024 * 1024) == pytest.approx(2 * 37_696 * 1024**2 / 1e9)
    rate = speed.matmul_gflops("fp32", size=256, repeats=1)
    assert np.isfinite(rate) and rate > 0.1  # even one slow core does 0.1 GFLOP/s
