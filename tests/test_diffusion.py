import math

import pytest
import torch

from dimgestor.config import get_preset
from dimgestor.model.diffusion import Diffusion, correlate, ddim_pairs, frame_noise, motion_noise, noise_kernel


def test_ddim_pairs_are_exact():
    assert ddim_pairs(8, 1000) == [(999, 874), (874, 749), (749, 624), (624, 499), (499, 374), (374, 249),
                                   (249, 124), (124, -1)]
    assert ddim_pairs(1, 1000) == [(999, -1)]
    assert ddim_pairs(4, 4) == [(3, 2), (2, 1), (1, 0), (0, -1)]
    for K in (3, 7, 50, 999):
        pairs = ddim_pairs(K, 1000)
        assert len(pairs) == K and pairs[0][0] == 999 and pairs[-1][1] == -1
        assert all(t > tp for t, tp in pairs) and all(a[1] == b[0] for a, b in zip(pairs, pairs[1:]))
    with pytest.raises(ValueError):
        ddim_pairs(0, 1000)
    with pytest.raises(ValueError):
        ddim_pairs(1001, 1000)


def test_a_configs_own_timesteps_set_its_ddim_steps_at_their_count():
    """ddim_timesteps (a progressively distilled student's): the pairs at their count, ddim_pairs at any other;
    refused unless strictly decreasing inside the schedule."""
    d = Diffusion(get_preset("tiny", n_steps=8, ddim_spacing="linspace", ddim_timesteps=(7, 2)))
    assert d.sampling_pairs("ddim", 2) == [(7, 2), (2, -1)]
    assert d.sampling_pairs("ddim", 4) == ddim_pairs(4, 8, "linspace") == [(7, 5), (5, 2), (2, 0), (0, -1)]
    for bad in ((2, 7), (8, 2), (7, 7), (3, -1), ()):
        with pytest.raises(ValueError, match="ddim_timesteps must be strictly decreasing steps in 0..7"):
            get_preset("tiny", n_steps=8, ddim_timesteps=bad)


def test_the_x0_that_reaches_a_point_is_the_one_whose_ddim_step_lands_there():
    """x0_reaching: from x_t, one deterministic DDIM step with that x0 lands on the given x_prev (the target of a
    progressively distilled step), and the last step's is x_prev itself."""
    d = Diffusion(get_preset("tiny", n_steps=8, schedule="cosine"))
    g = torch.Generator().manual_seed(0)
    x_t, x_prev = torch.randn(2, 5, 3, generator=g, dtype=torch.float64), torch.randn(2, 5, 3, generator=g,
                                                                                       dtype=torch.float64)
    for t, t_prev in ((7, 2), (5, 0), (2, -1)):
        x0 = d.x0_reaching(x_t, x_prev, t, t_prev)
        eps = (x_t - math.sqrt(d.a(t)) * x0) / math.sqrt(1 - d.a(t))
        assert torch.allclose(d.ddim_step(x_t, eps, t, t_prev, x0=x0)[0], x_prev, atol=1e-9)
    assert torch.equal(d.x0_reaching(x_t, x_prev, 2, -1), x_prev)


def test_schedules():
    lin = Diffusion(get_preset("tiny", schedule="linear"))
    assert lin.betas[0].item() == pytest.approx(1e-4) and lin.betas[-1].item() == pytest.approx(8e-2)
    sq = Diffusion(get_preset("tiny", schedule="sqrt_linear"))
    assert sq.betas[0].item() == pytest.approx(1e-4) and sq.betas[-1].item() == pytest.approx(8e-2)
    assert sq.betas[500] < lin.betas[500]  # linear in sqrt(beta) is convex in beta
    assert lin.a(-1) == 1.0 and 0 < lin.a(999) < lin.a(0) < 1


def test_cosine_short_chain_spreads_the_noise_levels():
    d = Diffusion(get_preset("tiny", n_steps=8, schedule="cosine"))
    a = [d.a(t) for t in range(8)]
    assert all(x > y for x, y in zip(a, a[1:]))  # noisier at every step
    assert 0.9 < a[0] < 1 and a[-1] < 1e-3  # the first level is nearly clean, the last is nearly pure noise
    snr = [x / (1 - x) for x in a[:-1]]
    ratios = [s1 / s2 for s1, s2 in zip(snr, snr[1:])]
    assert max(ratios) < 12  # no level is wasted: every step cuts the signal-to-noise ratio by a bounded factor


@pytest.mark.parametrize("prediction,schedule,n", [("eps", "linear", 1000), ("v", "linear", 1000),
                                                   ("x0", "linear", 1000), ("x0", "cosine", 8)])
def test_split_inverts_the_training_target(prediction, schedule, n):
    d = Diffusion(get_preset("tiny", prediction=prediction, schedule=schedule, n_steps=n))
    x0, eps = torch.randn(2, 5, 3, dtype=torch.float64), torch.randn(2, 5, 3, dtype=torch.float64)
    for t in sorted({0, min(3, n - 1), min(300, n - 2)}):
        tt = torch.full((2,), t)
        xt = d.q_sample(x0, tt, eps)
        e, x = d.split(d.target(x0, tt, eps), xt, t)
        assert torch.allclose(e, eps) and torch.allclose(x, x0)


def test_ddim_step_with_true_noise_recovers_the_forward_process():
    d = Diffusion(get_preset("tiny"))
    x0, eps = torch.randn(1, 4, 3, dtype=torch.float64), torch.randn(1, 4, 3, dtype=torch.float64)
    xt = d.q_sample(x0, torch.tensor([400]), eps)
    x_prev, x0_pred = d.ddim_step(xt, eps, 400, 200)  # eta = 0: deterministic, eq. 12
    assert torch.allclose(x0_pred, x0)
    assert torch.allclose(x_prev, d.q_sample(x0, torch.tensor([200]), eps))
    x_last, _ = d.ddim_step(xt, eps, 400, -1)
    assert torch.allclose(x_last, x0)


def test_ddpm_step_matches_eta_one_ddim_over_one_step():
    # DDIM with eta = 1 between consecutive steps is the DDPM ancestral step (Song et al., sec. 4.1)
    d = Diffusion(get_preset("tiny"))
    x0, eps, z = (torch.randn(1, 4, 3, dtype=torch.float64) for _ in range(3))
    xt = d.q_sample(x0, torch.tensor([50]), eps)
    a, _ = d.ddim_step(xt, eps, 50, 49, eta=1.0, noise=z, x0=x0)
    b = d.ddpm_step(xt, x0, 50, z)
    assert torch.allclose(a, b)


def test_frame_noise_is_a_function_of_frame_and_step_only():
    whole = frame_noise(7, 0, 100, 3, 16)
    parts = torch.cat([frame_noise(7, 0, 1, 3, 16), frame_noise(7, 1, 38, 3, 16), frame_noise(7, 39, 61, 3, 16)])
    assert torch.equal(whole, parts)
    assert not torch.equal(whole, frame_noise(8, 0, 100, 3, 16))
    assert not torch.equal(whole, frame_noise(7, 0, 100, 4, 16))
    assert torch.equal(frame_noise(7, 2**33 + 5, 3, 0, 4), frame_noise(7, 2**33 + 5, 3, 0, 4))


def test_frame_noise_is_standard_normal():
    z = frame_noise(0, 0, 2000, 0, 64).double()
    assert abs(z.mean().item()) < 0.01 and abs(z.std().item() - 1) < 0.01
    assert abs((z ** 4).mean().item() - 3) < 0.1  # normal kurtosis
    c = torch.corrcoef(torch.stack([z[:-1].flatten(), z[1:].flatten()]))[0, 1]
    assert abs(c.item()) < 0.01  # neighbouring frames independent
    assert abs(torch.corrcoef(torch.stack([z[:, 0], z[:, 1]]))[0, 1].item()) < 0.06


def test_training_loss_is_mse_on_the_target():
    from dimgestor.model.network import DiMGestor
    torch.manual_seed(0)
    m = DiMGestor(get_preset("tiny"))
    d = Diffusion(m.config)
    x0, noise = torch.randn(2, 6, 12), torch.randn(2, 6, 12)
    feats = torch.randn(2, 6 * 5 + 3, 20)
    t = torch.tensor([3, 900])
    loss = d.training_loss(m, x0, feats, t, noise)
    # at init the decoder is zero, so the loss is the mean square of the target
    assert math.isclose(loss.item(), d.target(x0, t, noise).pow(2).mean().item(), rel_tol=1e-5)


class _Oracle:
    """Stands in for the network: outputs the exact training target plus a chosen error."""

    def __init__(self, target, error):
        self.target, self.error = target, error

    def condition(self, feats):
        return torch.zeros(feats.shape[0], 64, 4), None

    def __call__(self, x_t, t, cond):
        return self.target + self.error, None


@pytest.mark.parametrize("prediction", ["eps", "v"])
def test_velocity_loss_penalises_jitter_not_offsets(prediction):
    d = Diffusion(get_preset("tiny", prediction=prediction))
    g = torch.Generator().manual_seed(0)
    x0, noise = torch.randn(3, 10, 5, generator=g), torch.randn(3, 10, 5, generator=g)
    t, feats = torch.tensor([5, 100, 300]), torch.zeros(3, 1, 1)
    target, c, w = d.target(x0, t, noise), 0.1, 2.0
    exact = d.training_loss(_Oracle(target, 0.0), x0, feats, t, noise, vel_weight=w)
    assert exact.item() == pytest.approx(0.0, abs=1e-10)
    offset = d.training_loss(_Oracle(target, c), x0, feats, t, noise, vel_weight=w)
    assert offset.item() == pytest.approx(c * c, rel=1e-5)  # a constant error moves no frame against the next
    sign = (-1.0) ** torch.arange(10)[None, :, None]
    jitter = d.training_loss(_Oracle(target, c * sign), x0, feats, t, noise, vel_weight=w)
    a = d.alphas_cumprod[t].float()
    # error e on the output is an x0 error of -sqrt(1-a) e (v) or -sqrt((1-a)/a) e (eps, whose term is weighted by a)
    per_sample = 4 * c * c * (1 - a)
    assert jitter.item() == pytest.approx(c * c + w * per_sample.mean().item(), rel=1e-4)
    assert d.training_loss(_Oracle(target, c * sign), x0, feats, t, noise).item() == pytest.approx(c * c, rel=1e-5)


def test_correlated_noise_is_exact_per_frame_unit_variance_and_smooth():
    for taps in (1, 3, 5):
        whole = motion_noise(11, -4, 90, 2, 6, taps)
        parts = torch.cat([motion_noise(11, -4, 1, 2, 6, taps), motion_noise(11, -3, 37, 2, 6, taps),
                           motion_noise(11, 34, 52, 2, 6, taps)])
        assert torch.equal(whole, parts)  # any window draws the same numbers: streaming stays exact
        z = motion_noise(0, 0, 20000, 0, 8, taps).double()
        assert abs(z.var().item() - 1) < 0.05 and abs(z.mean().item()) < 0.03
        lag1 = (z[1:] * z[:-1]).mean().item()
        k = noise_kernel(taps)
        assert lag1 == pytest.approx(float((k[1:] * k[:-1]).sum()), abs=0.03)  # correlated as the kernel says
    assert torch.equal(motion_noise(5, 0, 10, 1, 3, 1), frame_noise(5, 0, 10, 1, 3))  # taps 1: the paper's noise
    white = torch.randn(2, 10 + 4, 3, dtype=torch.float64)
    assert correlate(white, 5).shape == (2, 10, 3)
    d = Diffusion(get_preset("tiny", noise_taps=5))
    assert d.noise_like(torch.zeros(3, 40, 2)).shape == (3, 40, 2)


@pytest.mark.parametrize("order_weights", [(1.0, 0.0), (0.0, 1.0)])
def test_derivative_losses_penalise_jitter_not_offsets_for_x0(order_weights):
    d = Diffusion(get_preset("tiny", prediction="x0", schedule="cosine", n_steps=8))
    torch.manual_seed(0)
    x0 = torch.randn(2, 16, 12).cumsum(1) * 0.1
    feats, t, noise = torch.randn(2, 16 * 5 + 10, 20), torch.tensor([1, 5]), torch.randn(2, 16, 12)
    vel, acc = order_weights
    plain = d.training_loss(_Oracle(x0, 0.0), x0, feats, t, noise)
    sign = torch.tensor([1.0, -1.0]).repeat(8)[None, :, None]
    offset = d.training_loss(_Oracle(x0, 0.1), x0, feats, t, noise, vel_weight=vel, acc_weight=acc)
    jitter = d.training_loss(_Oracle(x0, 0.1 * sign), x0, feats, t, noise, vel_weight=vel, acc_weight=acc)
    assert plain == pytest.approx(0.0, abs=1e-12)
    assert offset == pytest.approx(0.01, rel=1e-4)  # a constant offset has no velocity or acceleration error
    assert jitter > 3 * offset  # an alternating error of the same size is penalised far more
