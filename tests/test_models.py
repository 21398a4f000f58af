"""Contract and math tests for every registered denoiser (tiny widths, 16-32 px, 2 samples)."""
from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from stores.contract import NUM_FEATURES
from training.errors import ConfigError, UnknownModelError
from training.models import build, get, names
from training.models.common import IN_FEATURES, gather, splat

TINY_UNET = dict(embed=8, context=8, unet_encoder=((8,), (8,), (8,)), unet_bottleneck=(8,),
                 unet_decoder=((8,), (8,), (8,)))


def tiny_cfg(name: str, **over) -> dict:
    """The model's own test-sized settings (its class's ``tiny``), with overrides."""
    return {**get(name).tiny, **over}


PAPER_MODELS = ["layer", "layer-w", "pixelgather", "samplesplat", "layer-optimized"]


def make_batch(b=2, s=2, h=24, w=20, seed=0, scale=1.0):
    g = torch.Generator().manual_seed(seed)
    rad = torch.rand(b, s, 3, h, w, generator=g) * scale
    feat = torch.rand(b, s, NUM_FEATURES, h, w, generator=g)
    feat[:, :, 3] *= 50.0                                            # depth in scene units
    return {"radiance": rad, "features": feat}


def kind_batch(model, b=2, h=24, w=20, seed=0, spp=2):
    """A random batch of the model's declared input kind."""
    spec = model.input_spec()
    return spec.input_kind.example_batch(b, spp, h, w, spec.frames, torch.Generator().manual_seed(seed))


def test_registry_has_the_paper_models():
    assert set(PAPER_MODELS) | {"nbg", "wskpn"} <= set(names())
    with pytest.raises(UnknownModelError) as e:
        build("no-such-model")
    assert str(e.value).startswith("unknown model 'no-such-model'; registered: ["), str(e.value)   # no KeyError quotes
    with pytest.raises(ConfigError, match="layers"):
        build("layer", layers=6)
    with pytest.raises(ConfigError, match="kernel_size"):
        build("pixelgather", kernel_size=4)


def _radiance_key(batch):
    return "layers" if "layers" in batch else "radiance"


def _hard_case(batch: dict, case: str) -> None:
    """Make ``batch`` (any input kind) a hard case in place."""
    rad = batch[_radiance_key(batch)]
    flat = rad.view(-1)
    if case == "fireflies":
        flat[:: max(1, flat.numel() // 7)] = 1e6
    elif case == "huge":
        rad.mul_(1e8)
    elif case == "zeros":
        for v in batch.values():
            if v.is_floating_point() and v.dim() >= 4:
                v.zero_()
    elif case == "zero_albedo":
        if "features" in batch:
            batch["features"][..., 4:7, :, :] = 0.0
        else:
            batch["albedo"].zero_()
    elif case == "nan":
        flat[:: max(1, flat.numel() // 11)] = float("nan")
        flat[3] = float("inf")


@pytest.mark.parametrize("name", names())
class TestModelContract:
    """Every registered model (a new model file is covered by being registered): shapes, rebuild from
    its config, its inference form, and finite forward AND backward on the hard inputs."""

    def test_shape_and_rebuild(self, name):
        torch.manual_seed(0)
        m = build(name, **tiny_cfg(name))
        batch = kind_batch(m)
        out = m(batch)
        if out.dim() == 5:                   # a recurrent model outputs every frame of its window
            assert out.shape[:2] == (2, m.input_spec().frames)
            out = out[:, -1]
            m_last = lambda mod, b: mod(b)[:, -1]           # noqa: E731
        else:
            m_last = lambda mod, b: mod(b)                  # noqa: E731
        assert out.shape == (2, 3, 24, 20) and out.dtype == torch.float32
        m2 = build(name, **m.config)
        m2.load_state_dict(m.state_dict())
        assert torch.equal(m_last(m2, batch), out)
        with torch.no_grad():
            fast_model = m.for_inference()
            fast = m_last(fast_model, batch)
        assert torch.allclose(fast, out, rtol=1e-4, atol=1e-5)
        convs = [p for p in fast_model.parameters() if p.dim() == 4]
        assert convs and all(p.is_contiguous(memory_format=torch.channels_last) for p in convs), \
            "the inference form's convolution weights are channels-last (the inputs' layout)"
        assert m.param_count() > 0 and m.fmas_per_pixel(8) > m.fmas_per_pixel(1) * 0.99
        assert m.input_spec().default_spp >= 1

    @pytest.mark.parametrize("where", [torch.float64, "meta"])
    def test_the_inference_form_stays_where_the_model_is(self, name, where):
        """Moved to float64, or to the ``meta`` device, then ``for_inference()``: every parameter and buffer
        follows (modules built after construction, such as WSKPN's fused blocks, included), and a forward
        runs there (on meta: meta tensors of the right shape)."""
        torch.manual_seed(0)
        m = build(name, **tiny_cfg(name)).to(where).for_inference()
        dev = torch.device("meta" if where == "meta" else "cpu")
        dtype = torch.float64 if where == torch.float64 else torch.float32
        tensors = dict(m.named_parameters()) | dict(m.named_buffers())
        strays = {k: (t.device, t.dtype) for k, t in tensors.items() if t.device != dev or t.dtype != dtype}
        assert tensors and not strays, strays
        batch = {k: v.to(dev, dtype if v.is_floating_point() else v.dtype) for k, v in kind_batch(m, h=16, w=16).items()}
        with torch.no_grad():
            out = m(batch)
        frames = (m.input_spec().frames,) if out.dim() == 5 else ()
        assert out.device == dev and out.dtype == dtype and out.shape == (2, *frames, 3, 16, 16)
        if where != "meta":
            assert torch.isfinite(out).all()

    def test_the_forward_pass_compiles_to_one_graph(self, name):
        """Dynamo traces the whole training-mode forward pass (a window of a recurrent model unrolled) as
        one graph: no break (a value read back, an unsupported call) splits it."""
        torch.manual_seed(0)
        m = build(name, **tiny_cfg(name, **({"frames": 2} if "frames" in get(name).tiny else {})))
        torch._dynamo.reset()
        explained = torch._dynamo.explain(m)(kind_batch(m, b=1, h=16, w=16))
        assert explained.graph_count == 1 and explained.graph_break_count == 0, explained.break_reasons

    @pytest.mark.gpu
    @pytest.mark.parametrize("precision", ["fp32", "bf16"])
    def test_the_inference_form_runs_on_cuda(self, name, precision):
        """Every model's inference form on a CUDA device, in fp32 and under bf16 autocast: its outputs stay
        on the device, finite, and (fp32) equal the CPU's within float rounding."""
        from training import accel
        torch.manual_seed(0)
        m = build(name, **tiny_cfg(name))
        batch = kind_batch(m)
        with torch.no_grad():
            ref = m.for_inference()(batch)
            gpu = accel.prepare(m, torch.device("cuda")).for_inference()
            with accel.autocast(torch.device("cuda"), precision):
                out = gpu({k: v.cuda() for k, v in batch.items()})
        assert out.is_cuda and torch.isfinite(out).all()
        if precision == "fp32":
            torch.testing.assert_close(out.cpu(), ref, rtol=1e-3, atol=1e-4)

    @pytest.mark.parametrize("case", ["fireflies", "huge", "zeros", "zero_albedo", "nan"])
    def test_stability(self, name, case):
        torch.manual_seed(1)
        m = build(name, **tiny_cfg(name))
        batch = kind_batch(m, seed=3)
        _hard_case(batch, case)
        rad = batch[_radiance_key(batch)].requires_grad_(True)
        ref = torch.rand(2, 3, 24, 20) * (1e8 if case == "huge" else 1.0)
        out = m(batch)
        assert torch.isfinite(out).all()
        if out.dim() == 5:                   # a recurrent model's window: every frame, judged on the last
            out = out[:, -1]
        loss = (torch.abs(out - ref) / (out.abs() + ref.abs() + 0.01)).mean()
        loss.backward()
        grads = [p.grad for p in m.parameters() if p.grad is not None]
        assert grads and all(torch.isfinite(g).all() for g in grads)
        assert torch.isfinite(rad.grad).all()
        if case == "zeros":
            assert torch.allclose(out, torch.zeros_like(out))


@pytest.mark.parametrize("name", [n for n in PAPER_MODELS if hasattr(get(n)(**get(n).tiny), "partitioner")])
def test_stability_with_every_sample_in_one_layer(name):
    """The partitioner's last layer outputs +-50 logits: every sample goes to layer 0."""
    torch.manual_seed(1)
    m = build(name, **tiny_cfg(name))
    last = m.partitioner[-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.fill_(-50.0)
        last.bias[0] = 50.0
    batch = make_batch(seed=3)
    batch["radiance"].requires_grad_(True)
    out = m(batch)
    assert torch.isfinite(out).all()
    out.mean().backward()
    assert torch.isfinite(batch["radiance"].grad).all()


# -- kernel application: vectorised unfold/fold against an explicit loop --------------------------

def _loop_gather(x, k, ks):
    b, c, h, w = x.shape
    r = ks // 2
    out = torch.zeros_like(x)
    for y in range(h):
        for xx in range(w):
            for t in range(ks * ks):
                dy, dx = t // ks - r, t % ks - r
                if 0 <= y + dy < h and 0 <= xx + dx < w:
                    out[:, :, y, xx] += k[:, t, y, xx, None] * x[:, :, y + dy, xx + dx]
    return out


def _loop_splat(x, k, ks):
    b, c, h, w = x.shape
    r = ks // 2
    out = torch.zeros_like(x)
    for y in range(h):
        for xx in range(w):
            for t in range(ks * ks):
                dy, dx = t // ks - r, t % ks - r
                if 0 <= y + dy < h and 0 <= xx + dx < w:
                    out[:, :, y + dy, xx + dx] += k[:, t, y, xx, None] * x[:, :, y, xx]
    return out


def test_gather_and_splat_match_explicit_loops():
    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, 3, 7, 6, generator=g, dtype=torch.float64)
    k = torch.rand(2, 9, 7, 6, generator=g, dtype=torch.float64)
    assert torch.allclose(gather(x, k, 3), _loop_gather(x, k, 3))
    assert torch.allclose(splat(x, k, 3), _loop_splat(x, k, 3))
    # adjointness: <gather(x), y> == <x, splat(y)> for the same kernels
    y = torch.rand(2, 3, 7, 6, generator=g, dtype=torch.float64)
    assert torch.allclose((gather(x, k, 3) * y).sum(), (x * splat(y, k, 3)).sum())


# -- limits where the math says models agree --------------------------------------------------------

@pytest.mark.parametrize("name,layers", [("layer", 1), ("layer", 2), ("layer", 5), ("layer-w", 1)])
def test_kernel_size_one_composites_to_the_pixel_mean(name, layers):
    """With 1x1 kernels, alpha compositing with appendix-A occupancy (and weighted compositing)
    reproduces the per-pixel sample mean exactly, whatever the learned partition (weighted
    compositing only with one layer: its per-layer kernels re-weight layers)."""
    torch.manual_seed(0)
    m = build(name, **tiny_cfg(name, kernel_size=1, layers=layers))
    batch = make_batch(s=4)
    out = m(batch)
    assert torch.allclose(out, batch["radiance"].mean(dim=1), rtol=1e-4, atol=1e-5)


def _zero_kernels(mlp):
    with torch.no_grad():
        mlp[-1].weight.zero_()
        mlp[-1].bias.zero_()


def _box_oracle(mean, ks):
    """Normalised box filter over the in-frame neighbourhood (independent: avg_pool2d)."""
    return F.avg_pool2d(mean, ks, stride=1, padding=ks // 2, count_include_pad=False)


def test_layer1_samplesplat_pixelgather_agree_with_constant_kernels():
    """Kernel generators that output 0 give all-ones kernels: LAYER with 1 layer, SAMPLESPLAT and
    PIXELGATHER all reduce to the normalised 5x5 box filter of the per-pixel mean."""
    torch.manual_seed(0)
    batch = make_batch(s=3, seed=5)
    oracle = _box_oracle(batch["radiance"].mean(dim=1), 5)
    for name in ("layer", "samplesplat", "pixelgather"):
        m = build(name, **tiny_cfg(name, **({"layers": 1} if name == "layer" else {})))
        _zero_kernels(m.kernel_gen)
        assert torch.allclose(m(batch), oracle, rtol=1e-4, atol=1e-5), name


def test_layer1_equals_samplesplat_when_samples_agree():
    """If every sample of a pixel is identical, LAYER with one layer (kernel from the mean embedding)
    and SAMPLESPLAT (a kernel per sample) with the same weights produce the same image."""
    torch.manual_seed(0)
    one = make_batch(s=1, seed=7)
    batch = {k: v.expand(-1, 4, -1, -1, -1).contiguous() for k, v in one.items()}
    layer = build("layer", **tiny_cfg("layer", layers=1))
    ss = build("samplesplat", **tiny_cfg("samplesplat"))
    shared = {k: v for k, v in layer.state_dict().items() if not k.startswith("partitioner")}
    ss.load_state_dict(shared)
    a, b = layer(batch), ss(batch)
    assert torch.allclose(a, b, rtol=1e-4, atol=1e-5)
    assert not torch.allclose(a, batch["radiance"].mean(dim=1), atol=1e-3)   # kernels do filter


def test_kernel_exponent_never_overflows():
    m = build("layer", **tiny_cfg("layer"))
    with torch.no_grad():
        m.kernel_gen[-1].bias.fill_(1e4)                  # exp(1e4) would be inf without max-subtraction
        m.kernel_gen[-1].bias[0] = 2e4
    out = m(make_batch())
    assert torch.isfinite(out).all()


def test_padded_unet_handles_odd_sizes():
    m = build("layer-optimized", **tiny_cfg("layer-optimized"))
    out = m(make_batch(h=17, w=13))
    assert out.shape == (2, 3, 17, 13) and torch.isfinite(out).all()


# -- FMA counts: analytic against torch's FlopCounterMode (an independent count of conv FLOPs) ------

@pytest.mark.parametrize("name", ["layer", "pixelgather", "samplesplat"])
def test_conv_fmas_match_flop_counter(name):
    from torch.utils.flop_counter import FlopCounterMode

    m = build(name, **tiny_cfg(name))
    s, h, w = 2, 32, 32
    with torch.no_grad(), FlopCounterMode(display=False) as fc:
        m(make_batch(b=1, s=s, h=h, w=w))
    counts = fc.get_flop_counts()["Global"]
    # 1x1 convolutions run as bmm (training.models.common.MLP); samplesplat's per-pixel sample
    # reduction is a bmm too (4 x S times S x k2)
    flops = sum(v for k, v in counts.items() if "convolution" in str(k) or "bmm" in str(k))
    from training.models.common import conv_fmas
    ctx = m.unet.cout
    if name == "pixelgather":
        analytic = conv_fmas(m.reducer) + m.unet.fmas_per_pixel() + conv_fmas(m.kernel_gen)
    elif name == "samplesplat":
        # kernel generator on cat(sample embedding, context): the context part once per pixel
        analytic = s * conv_fmas(m.reducer) + m.unet.fmas_per_pixel() \
            + s * conv_fmas(m.kernel_gen) - (s - 1) * ctx * m.kernel_gen[0].out_channels \
            + 4 * s * m.kernel_size ** 2
    else:
        analytic = s * conv_fmas(m.reducer) + m.unet.fmas_per_pixel() \
            + s * conv_fmas(m.partitioner) - (s - 1) * ctx * m.partitioner[0].out_channels \
            + m.layers * conv_fmas(m.kernel_gen) - (m.layers - 1) * ctx * m.kernel_gen[0].out_channels
    assert flops == pytest.approx(2 * analytic * h * w, rel=1e-9)


def test_paper_defaults():
    """Defaults are the paper's: 20 inputs, 32 embedding, 128 context, 17x17 kernels, 2 layers."""
    m = build("layer")
    assert m.reducer[0].in_channels == IN_FEATURES == 20 and m.reducer[0].out_channels == 32
    assert [c.out_channels for c in m.partitioner if isinstance(c, torch.nn.Conv2d)] == [32, 16, 2]
    assert [c.out_channels for c in m.kernel_gen if isinstance(c, torch.nn.Conv2d)] == [128, 128, 289]
    assert m.kernel_gen[0].in_channels == 160 and m.unet.final.out_channels == 128
    opt = build("layer-optimized")
    assert [g[-1].out_channels for g in opt.kernel_gens] == [26, 26, 26]
    assert all(c.out_channels == 32 for g in opt.kernel_gens for c in g[:-1] if isinstance(c, torch.nn.Conv2d))
    assert opt.fmas_per_pixel(8) < m.fmas_per_pixel(8) / 2
    pg = build("pixelgather")
    assert pg.reducer[0].in_channels == 40


def test_mlp_shared_split_equals_broadcast_concat():
    """MLP(items, shared) computes the shared input's part of the first layer once per pixel; it must
    equal running the same 1x1 convolutions (torch's conv2d) on the materialised concatenation."""
    import torch.nn.functional as F

    from training.models.common import mlp
    torch.manual_seed(3)
    m = mlp(7 + 5, (16, 8), 3)
    items, shared = torch.randn(2, 4, 7, 6, 5), torch.randn(2, 5, 6, 5)
    got = m(items, shared)
    x = torch.cat((items, shared.unsqueeze(1).expand(2, 4, 5, 6, 5)), dim=2).reshape(8, 12, 6, 5)
    for layer in m:
        x = F.conv2d(x, layer.weight, layer.bias) if isinstance(layer, torch.nn.Conv2d) else F.leaky_relu(x, 0.01)
    assert got.shape == (2, 4, 3, 6, 5)
    torch.testing.assert_close(got, x.view(2, 4, 3, 6, 5), rtol=1e-5, atol=1e-5)
    assert m.fmas(items=4, shared=5) == 4 * (7 * 16 + 16 * 8 + 8 * 3) + 5 * 16


@pytest.mark.parametrize("name", ["layer", "pixelgather", "samplesplat"])
def test_kernels_start_as_a_gaussian_not_a_box(name):
    """A fresh 17x17 model's kernels are close to the Gaussian of ``kernel_sigma`` (bias init), not
    the box filter that zero biases give; kernel_sigma 0 restores the box (all taps equal)."""
    torch.manual_seed(0)
    batch = make_batch(b=1, s=2, h=32, w=32)
    r = torch.arange(17.0) - 8
    d2 = (r[:, None] ** 2 + r[None, :] ** 2).flatten()
    for sigma in (2.0, 0.0):
        m = build(name, kernel_sigma=sigma, **TINY_UNET)
        with torch.no_grad():
            if name == "pixelgather":
                k = m.pixel_kernels(batch["radiance"], batch["features"])            # B k2 H W
            elif name == "samplesplat":
                k = m.sample_kernels(batch["radiance"], batch["features"])[:, 0]
            else:
                e, ctx = m.embed_samples(batch["radiance"], batch["features"])
                k = m.layer_kernels(e[:, :2], ctx)[:, 0]
        p = (k / k.sum(dim=1, keepdim=True)).mean(dim=(0, 2, 3))
        want = torch.exp(-d2 / (2 * sigma * sigma)) if sigma else torch.ones(289)
        torch.testing.assert_close(p, want / want.sum(), rtol=0.0, atol=5e-3)   # box vs Gaussian: 0.036
    with pytest.raises(ConfigError, match="kernel_sigma"):
        build(name, kernel_sigma=-1)


def test_soft_bound_caps_the_context_scale():
    """soft_bound is the identity for small features and caps the per-pixel RMS at 1 for huge ones,
    so the U-net cannot scale the context up without limit (LAYER's reached 1e26 without it)."""
    from training.models.common import soft_bound
    small = torch.randn(2, 16, 5, 5) * 1e-3
    torch.testing.assert_close(soft_bound(small), small, rtol=1e-5, atol=0)
    huge = torch.randn(2, 16, 5, 5) * 1e20
    rms = soft_bound(huge).square().mean(dim=1).sqrt()
    assert torch.isfinite(rms).all() and (rms <= 1.0 + 1e-6).all() and (rms > 0.99).all()
    m = build("layer", **TINY_UNET)
    with torch.no_grad():
        m.unet.final.weight.mul_(1e15)
        _, ctx = m.embed_samples(*make_batch().values())
    assert ctx.square().mean(dim=1).sqrt().max() <= 1.0 + 1e-6


def test_replicate_pad_compiled_is_a_gather_of_the_same_values_and_gradients():
    """``replicate_pad`` compiled (a gather at clamped indices, which Inductor's backward handles where its
    replication_pad2d_backward fails on channels-last gradients) equals ``F.pad(mode="replicate")``."""
    from training.models.common import replicate_pad
    x = torch.rand(2, 3, 7, 9, requires_grad=True).contiguous(memory_format=torch.channels_last)
    for pad in ((2, 2, 2, 2), (0, 3, 0, 1)):
        want = F.pad(x, pad, mode="replicate")
        got = torch.compile(lambda t: replicate_pad(t, pad), backend="eager", fullgraph=True)(x)
        g = torch.rand_like(want)
        assert torch.equal(got, want) and torch.equal(replicate_pad(x, pad), want)
        torch.testing.assert_close(torch.autograd.grad(got, x, g)[0], torch.autograd.grad(want, x, g)[0])
