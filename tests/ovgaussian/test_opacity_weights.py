"""Opacity weights of the 3D-to-text cross-entropy (``LossConfig.opacity_power``): the weights, the weighted loss
against its reference, every path of a training step against the one-piece weighted sum, and the invariance that
makes the oracle control independent of the option (Gaussians sharing one opacity)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from ovgaussian.data.scene_source import InMemorySource
from ovgaussian.data.training_data import TrainingData
from ovgaussian.run.config import DataConfig, LossConfig
from ovgaussian.text.vocabulary import training_vocabulary
from ovgaussian.train.losses import (
    masked_cross_entropy, opacity_row_weights, reference_text_cross_entropy, text_cross_entropy,
)
from seggaussian.core.constants import IGNORE_LABEL

from test_train import make_scene, text_stub, tiny_config, tiny_model_config


def test_weights_are_opacity_powers_with_mean_one_over_the_counted_rows():
    logits = torch.tensor([-3.0, 0.0, 2.0, 5.0, -1.0])
    counted = torch.tensor([True, True, True, False, True])
    weights = opacity_row_weights(logits, counted, 0.5)
    raw = torch.sigmoid(logits.double()) ** 0.5
    torch.testing.assert_close(weights.double(), raw / raw[counted].mean(), rtol=1e-7, atol=0)
    assert weights.dtype == torch.float32 and float(weights[counted].double().mean()) == pytest.approx(1.0, rel=1e-6)
    assert float(weights[0]) < float(weights[1]) < float(weights[2])  # fainter: less weight


@pytest.mark.parametrize("value", [-4.0, 0.3, 2.0, 2.9444389791664403])  # 2.944...: the oracle sample's 0.95
@pytest.mark.parametrize("rows", [1, 7, 40_000])
def test_one_shared_opacity_gives_weight_exactly_one(value, rows):
    weights = opacity_row_weights(torch.full((rows,), value), torch.ones(rows, dtype=torch.bool), 0.5)
    assert torch.equal(weights, torch.ones(rows))


def test_weights_degenerate_inputs():
    logits = torch.tensor([1.0, -2.0])
    assert torch.equal(opacity_row_weights(logits, torch.tensor([True, True]), 0.0), torch.ones(2))
    assert torch.equal(opacity_row_weights(logits, torch.tensor([False, False]), 1.0), torch.ones(2))  # none counted
    assert opacity_row_weights(torch.zeros(0), torch.zeros(0, dtype=torch.bool), 1.0).shape == (0,)
    transparent = opacity_row_weights(torch.full((3,), -torch.inf), torch.ones(3, dtype=torch.bool), 1.0)
    assert torch.equal(transparent, torch.ones(3))  # all at opacity 0: no NaN, nothing preferred
    extreme = opacity_row_weights(torch.tensor([-1e4, 0.0, 1e4]), torch.ones(3, dtype=torch.bool), 2.0)
    assert torch.isfinite(extreme).all() and float(extreme[0]) == 0.0
    with pytest.raises(ValueError, match="opacity_power"):
        opacity_row_weights(logits, torch.tensor([True, True]), -0.5)


@pytest.mark.parametrize("seed", range(3))
def test_row_weighted_cross_entropy_matches_reference_forward_and_backward(seed):
    g = torch.Generator().manual_seed(seed)
    logits = torch.randn(30, 7, generator=g, dtype=torch.float64) * 4
    labels = torch.randint(0, 5, (30,), generator=g)
    labels[torch.rand(30, generator=g) < 0.3] = IGNORE_LABEL
    class_weights = torch.rand(7, generator=g, dtype=torch.float64) + 0.5
    row_weights = torch.rand(30, generator=g, dtype=torch.float64) * 2
    for columns in (None, torch.tensor([5, 6])):
        loss, count = text_cross_entropy(logits, labels, class_weights, columns, 0.7, row_weights)
        assert count == (30 if columns is not None else int((labels != IGNORE_LABEL).sum()))
        expected = reference_text_cross_entropy(logits.tolist(), labels.tolist(), class_weights.tolist(),
                                                None if columns is None else [5, 6], 0.7, row_weights.tolist())
        assert float(loss) == pytest.approx(expected, rel=1e-12)
        leaf = logits.clone().requires_grad_(True)
        assert torch.autograd.gradcheck(
            lambda x: text_cross_entropy(x, labels, class_weights, columns, 0.7, row_weights)[0], (leaf,))
    # weights of 1 change nothing, bitwise
    ones = torch.ones(30, dtype=torch.float64)
    assert torch.equal(masked_cross_entropy(logits, labels, class_weights, ones)[0],
                       masked_cross_entropy(logits, labels, class_weights)[0])


def _samples(opacity: str):
    """Two training samples of the test scenes: their own shared opacity (``shared``) or varied opacities."""
    voc = training_vocabulary(20)
    data = TrainingData(InMemorySource([make_scene(0), make_scene(1)]), DataConfig(blend_top_k=8, pixels_per_view=200),
                        voc)
    samples = [data.sample(s, np.random.default_rng(i)) for i, s in enumerate(("scene00", "scene01"))]
    if opacity == "varied":
        g = torch.Generator().manual_seed(3)
        samples = [s._replace(opacity_logits=torch.randn(len(s.means), generator=g) * 2.5) for s in samples]
    return samples


def _loss_and_grads(samples, config, chunks: int | None = None, monkeypatch=None):
    from ovgaussian.run.checkpoint import build_network
    import ovgaussian.model.network as model_module
    import ovgaussian.train.step_losses as step_losses_module

    if chunks is not None:  # several chunks, the last one short, on every chunked path
        real, real_eager = model_module.checkpointed_rows, step_losses_module.eager_row_sum
        monkeypatch.setattr(model_module, "checkpointed_rows",
                            lambda fn, *t, chunk_rows=None: real(fn, *t, chunk_rows=chunks, min_rows=0))
        monkeypatch.setattr(step_losses_module, "eager_row_sum",
                            lambda fn, rows, params: real_eager(fn, rows, params, chunk_rows=chunks, min_rows=0))
    torch.manual_seed(0)
    net = build_network(tiny_model_config(12)).train()
    terms = step_losses_module.batch_losses(net, samples, text_stub(), config, False, "cpu")
    loss = sum(t.total for t in terms)
    loss.backward()
    return terms, {n: p.grad.clone() for n, p in net.named_parameters() if p.grad is not None}


def _config(opacity_power: float, lovasz_weight: float = 0.0):
    config = tiny_config(Path("unused"), 1)
    return replace(config, loss=replace(config.loss, opacity_power=opacity_power, lovasz_weight=lovasz_weight))


@pytest.mark.parametrize("lovasz_weight", [0.0, 0.5])
def test_the_step_s_3d_term_is_the_opacity_weighted_mean(lovasz_weight):
    """Each scene's 3D term equals the cross-entropy of its labelled Gaussians, each term times its opacity weight,
    over their count (plus the unweighted Lovasz term), computed in one piece from the network's vectors."""
    from ovgaussian.run.checkpoint import build_network
    from ovgaussian.train.losses import lovasz_softmax
    from ovgaussian.train.step_losses import batch_losses, decoded_text_logits, network_inputs

    samples = _samples("varied")
    torch.manual_seed(0)
    net = build_network(tiny_model_config(12)).eval()
    with torch.no_grad():
        plain = batch_losses(net, samples, text_stub(), _config(0.0, lovasz_weight), False, "cpu")
        weighted = batch_losses(net, samples, text_stub(), _config(0.5, lovasz_weight), False, "cpu")
        semantic = net(*network_inputs(samples, "cpu"))
    start = 0
    for sample, a, b in zip(samples, plain, weighted):
        rows = semantic[start:start + len(sample.means)]
        start += len(sample.means)
        with torch.no_grad():
            logits = decoded_text_logits(net.phi, rows, text_stub(), 0.1)
        labelled = sample.labels != IGNORE_LABEL
        opacity = torch.sigmoid(sample.opacity_logits.double())[labelled] ** 0.5
        nll = -torch.log_softmax(logits.double()[labelled], 1).gather(1, sample.labels[labelled, None])[:, 0]
        expected = float((opacity / opacity.mean() * nll).mean())
        if lovasz_weight:
            expected += lovasz_weight * float(lovasz_softmax(logits, sample.labels))
        assert float(b.text_3d) == pytest.approx(expected, rel=1e-5)
        assert float(b.text_3d) != pytest.approx(float(a.text_3d), rel=1e-3)  # the weights change it
        assert b.count_3d == a.count_3d and float(b.text_2d) == float(a.text_2d)  # the 2D terms are not weighted


@pytest.mark.parametrize("lovasz_weight", [0.0, 0.5])
def test_chunked_paths_equal_the_whole_with_weights(monkeypatch, lovasz_weight):
    """The eager path (text loss alone) and the checkpointed one (with Lovasz) give the one-piece weighted loss and
    its gradients when the rows are cut into chunks."""
    samples, config = _samples("varied"), _config(0.5, lovasz_weight)
    whole_terms, whole_grads = _loss_and_grads(samples, config)
    chunk_terms, chunk_grads = _loss_and_grads(samples, config, chunks=37, monkeypatch=monkeypatch)
    for a, b in zip(whole_terms, chunk_terms):
        torch.testing.assert_close(b.text_3d, a.text_3d, rtol=1e-5, atol=1e-6)
    assert chunk_grads.keys() == whole_grads.keys()
    for name, grad in whole_grads.items():
        scale = float(grad.abs().max())
        torch.testing.assert_close(chunk_grads[name], grad, rtol=1e-4, atol=1e-6 + 1e-5 * scale, msg=name)


@pytest.mark.parametrize("lovasz_weight", [0.0, 0.5])
def test_a_shared_opacity_makes_the_option_change_nothing_bitwise(lovasz_weight):
    """Gaussians that all share one opacity (the oracle sample) train bitwise as without the option: the oracle
    control of the profile does not depend on it."""
    samples = _samples("shared")
    assert all(len(torch.unique(s.opacity_logits)) == 1 for s in samples)
    off_terms, off_grads = _loss_and_grads(samples, _config(0.0, lovasz_weight))
    on_terms, on_grads = _loss_and_grads(samples, _config(0.5, lovasz_weight))
    for a, b in zip(off_terms, on_terms):
        assert torch.equal(a.text_3d, b.text_3d) and torch.equal(a.total, b.total)
    assert all(torch.equal(on_grads[n], g) for n, g in off_grads.items())


def test_a_3d_loss_subset_reads_the_scene_s_weights_at_its_rows():
    """With a 3D-loss subset (``DataConfig.loss_gaussians``) each drawn Gaussian keeps the weight it has in its whole
    scene (mean 1 over the scene's labelled Gaussians, not over the subset)."""
    from ovgaussian.run.checkpoint import build_network
    from ovgaussian.train.step_losses import batch_losses, decoded_text_logits, network_inputs

    voc = training_vocabulary(20)
    data = TrainingData(InMemorySource([make_scene(0)]),
                        DataConfig(blend_top_k=8, pixels_per_view=200, loss_gaussians=90), voc)
    sample = data.sample("scene00", np.random.default_rng(0))
    sample = sample._replace(opacity_logits=torch.randn(len(sample.means), generator=torch.Generator().manual_seed(4)))
    assert sample.loss_rows is not None and 0 < len(sample.loss_rows) < len(sample.means)
    torch.manual_seed(0)
    net = build_network(tiny_model_config(12)).eval()
    with torch.no_grad():
        [term] = batch_losses(net, [sample], text_stub(), _config(0.5), False, "cpu")
        logits = decoded_text_logits(net.phi, net(*network_inputs([sample], "cpu")), text_stub(), 0.1)
    labelled = sample.labels != IGNORE_LABEL
    weights = torch.sigmoid(sample.opacity_logits.double()) ** 0.5
    weights = weights / weights[labelled].mean()
    rows = sample.loss_rows[labelled[sample.loss_rows]]
    nll = -torch.log_softmax(logits.double()[rows], 1).gather(1, sample.labels[rows, None])[:, 0]
    assert term.count_3d == len(rows)
    assert float(term.text_3d) == pytest.approx(float((weights[rows] * nll).mean()), rel=1e-5)
