"""The losses of one OVGaussian training step: network inputs, ``M = W S`` at the sampled pixels, and per scene
the 3D-to-text, 2D-to-text and visual-semantic (cosine) terms (``ovgaussian.train.losses`` holds the formulas).

Per scene: 3D-to-text CE on ``phi(s)``; ``M = render_features(W, s)`` at the sampled pixels; 2D-to-text CE on
``phi(M)``; cosine loss of ``psi(M)`` against the MaskCLIP teacher on covered pixels.

Transductive runs (``unlabelled_columns`` given, ``LossConfig.unlabelled_as_unseen``): the text embeddings hold
the seen and then the unseen classes; the Gaussians without a seen label and the covered pixels without one add
the partial-label term over the unseen columns to the 3D and 2D cross-entropies.
"""

from __future__ import annotations

from typing import Sequence

import torch

from ovgaussian.model import network as model
from ovgaussian.data.training_data import SceneSample
from ovgaussian.train.eager_adapter import semantic_with_row_loss
from ovgaussian.train.eager_rows import eager_row_sum
from ovgaussian.train.gram_logits import GramTerms, gram_terms, gram_text_logits, is_gram_decoder
from ovgaussian.train.losses import (
    combine_losses, compute_text_logits, lovasz_softmax, masked_cosine_loss, opacity_row_weights, text_cross_entropy,
)
from ovgaussian.run.config import TrainConfig
from seggaussian.core.constants import IGNORE_LABEL
from seggaussian.render import BlendWeights, render_features

#: A pixel takes part in the cosine loss when its kept blend weights sum to at least this (the rendered
#: semantic vector is then mostly made of Gaussians, not of the empty background).
COVERAGE_MIN = 0.5


def network_inputs(samples: Sequence[SceneSample], device) -> tuple["torch.Tensor", "torch.Tensor", "torch.Tensor"]:
    """Concatenated ``means [N, 3]``, ``attributes [N, 11]`` and ``batch_index [N]`` of the scenes."""
    means = torch.cat([s.means for s in samples])
    attributes = model.gaussian_attributes({
        "quats": torch.cat([s.quats for s in samples]),
        "log_scales": torch.cat([s.log_scales for s in samples]),
        "opacity_logits": torch.cat([s.opacity_logits for s in samples]),
        "sh": torch.cat([s.sh_dc for s in samples])[:, None, :],
    })
    batch_index = torch.cat([torch.full((len(s.means),), i, dtype=torch.int64) for i, s in enumerate(samples)])
    return means.to(device), attributes.to(device), batch_index.to(device)


def render_pixels(
    pixel_ids: "torch.Tensor",  # [P, K]
    pixel_weights: "torch.Tensor",  # [P, K]
    semantic: "torch.Tensor",  # [N, S]
) -> "torch.Tensor":  # [P, S]
    """``M = W S`` at the sampled pixels, through ``seggaussian.render.render_features`` (a P x 1 image)."""
    blend = BlendWeights(pixel_ids[:, None, :], pixel_weights[:, None, :],
                         torch.zeros(pixel_ids.shape[0], 1, device=pixel_ids.device))
    return render_features(blend, semantic)[:, 0]


def render_pixels_reference(pixel_ids, pixel_weights, semantic):
    """Slow reference of :func:`render_pixels`: one pixel and one contributor at a time."""
    out = torch.zeros(pixel_ids.shape[0], semantic.shape[1], dtype=semantic.dtype)
    for p in range(pixel_ids.shape[0]):
        for k in range(pixel_ids.shape[1]):
            gid = int(pixel_ids[p, k])
            if gid >= 0:
                out[p] = out[p] + pixel_weights[p, k] * semantic[gid]
    return out


def decoded_text_logits(
    phi,
    semantic: "torch.Tensor",  # [N, S]
    text_embeddings: "torch.Tensor",  # [C, D]
    temperature: float,
) -> "torch.Tensor":  # [N, C]
    """``compute_text_logits(phi(semantic), text_embeddings, temperature)`` without phi's ``[N, D]`` output: the Gram
    form of ``ovgaussian.train.gram_logits`` for ``phi = Linear o ReLU o Linear``; any other ``phi`` takes the
    direct expression (the reference)."""
    return _text_logits_fn(phi, text_embeddings, temperature)(semantic)


def _text_logits_fn(phi, text_embeddings: "torch.Tensor", temperature: float):
    """``rows [n, S] -> [n, C]`` logits of :func:`decoded_text_logits`, with the Gram terms built once (outside any
    checkpointed chunk: the chunks share them and their small products are not recomputed)."""
    terms = gram_terms(phi, text_embeddings)  # the logits functions check the temperature
    if terms is None:
        return lambda rows: compute_text_logits(phi(rows), text_embeddings, temperature)
    return lambda rows: gram_text_logits(rows, terms, temperature)


def text_cross_entropy_3d(
    phi,
    semantic: "torch.Tensor",  # [N, S] semantic vectors of the labelled Gaussians (every Gaussian: transductive)
    labels: "torch.Tensor",  # [N] seen-class index (IGNORE_LABEL: an unlabelled row, with unlabelled_columns)
    text_embeddings: "torch.Tensor",  # [C, D]
    temperature: float,
    class_weights: "torch.Tensor | None" = None,  # [C]
    unlabelled_columns: "torch.Tensor | None" = None,  # [U]
    unlabelled_weight: float = 1.0,
    row_weights: "torch.Tensor | None" = None,  # [N] weight of each row's term (LossConfig.opacity_power)
) -> tuple["torch.Tensor", int]:
    """3D-to-text cross-entropy (mean over the rows, count): ``text_cross_entropy`` of
    ``compute_text_logits(phi(semantic))``, summed over row chunks so that phi's activations are never held whole:
    for the Gram-form decoder (``ovgaussian.train.gram_logits``) each chunk's gradients are taken in the forward
    (``ovgaussian.train.eager_rows``: one forward per chunk), for any other ``phi`` under activation checkpointing
    (``ovgaussian.model.network.checkpointed_rows``)."""
    count = text_3d_count(labels, unlabelled_columns)
    terms = gram_terms(phi, text_embeddings)

    def chunk_sum(logits, rows_labels, rows_weights=None):
        return text_sum(logits, rows_labels, class_weights, unlabelled_columns, unlabelled_weight, rows_weights)

    per_row = (semantic, labels) if row_weights is None else (semantic, labels, row_weights)
    extra = len(per_row) - 2  # the weights' chunk, when there are weights, comes before the Gram terms

    def gram_chunk_sum(rows, rows_labels, *rest):
        return chunk_sum(gram_text_logits(rows, GramTerms(*rest[extra:]), temperature), rows_labels, *rest[:extra])

    if terms is not None:
        total = eager_row_sum(gram_chunk_sum, per_row, tuple(terms))
    else:
        sums = model.checkpointed_rows(  # through the module: tests patch it
            lambda rows, rows_labels, *rows_weights: chunk_sum(
                compute_text_logits(phi(rows), text_embeddings, temperature), rows_labels, *rows_weights), *per_row)
        total = sum(sums)
    return (total * 0.0, 0) if count == 0 else (total / count, count)


def text_3d_count(labels: "torch.Tensor", unlabelled_columns: "torch.Tensor | None") -> int:
    """Rows the 3D text term counts: the labelled ones, or every one in a transductive run (``unlabelled_columns``)."""
    return int((labels != IGNORE_LABEL).sum()) if unlabelled_columns is None else int(labels.shape[0])


def text_sum(logits, labels, class_weights=None, unlabelled_columns=None, unlabelled_weight: float = 1.0,
             row_weights=None):
    """``text_cross_entropy`` of the rows as a sum (mean x count), so that row chunks add up."""
    mean, count = text_cross_entropy(logits, labels, class_weights, unlabelled_columns, unlabelled_weight,
                                     row_weights)
    return mean * count


def text_and_lovasz_3d(
    phi,
    semantic: "torch.Tensor",  # [N, S]
    labels: "torch.Tensor",  # [N]
    text_embeddings: "torch.Tensor",  # [C, D]
    temperature: float,
    lovasz_weight: float,
    class_weights: "torch.Tensor | None" = None,
    unlabelled_columns: "torch.Tensor | None" = None,
    unlabelled_weight: float = 1.0,
    row_weights: "torch.Tensor | None" = None,  # [N] weight of each row's cross-entropy term (not the Lovasz's)
) -> tuple["torch.Tensor", int]:
    """:func:`text_cross_entropy_3d` plus ``lovasz_weight`` x the Lovasz-softmax of the same logits: the ``[N, C]``
    logits are decoded once, in row chunks under activation checkpointing (phi's hidden rows never held whole, as
    in the cross-entropy alone), and both terms read them. The Lovasz term is skipped where nothing is counted."""
    chunks = model.checkpointed_rows(_text_logits_fn(phi, text_embeddings, temperature), semantic)
    logits = chunks[0] if len(chunks) == 1 else torch.cat(chunks)
    mean, count = text_cross_entropy(logits, labels, class_weights, unlabelled_columns, unlabelled_weight,
                                     row_weights)
    if count == 0:
        return logits.sum() * 0.0, 0
    return mean + lovasz_weight * lovasz_softmax(logits, labels), count


def needed_rows(sample: SceneSample) -> "torch.Tensor | None":
    """``[R]`` increasing rows of the Gaussians a step needs of this scene when it draws a 3D-loss subset
    (``sample.loss_rows``): the subset and every contributor of the sampled pixels; None without a subset."""
    if sample.loss_rows is None:
        return None
    contributors = sample.pixel_ids[sample.pixel_ids >= 0]
    return torch.unique(torch.cat([sample.loss_rows, contributors]))  # sorted


def scene_losses(net, semantic: "torch.Tensor", sample: SceneSample, text_embeddings: "torch.Tensor",
                 config: TrainConfig, use_teacher: bool, class_weights: "torch.Tensor | None" = None,
                 unlabelled_columns: "torch.Tensor | None" = None, rows: "torch.Tensor | None" = None,
                 text_3d: "tuple[torch.Tensor, int] | None" = None):
    """:class:`ovgaussian.train.losses.LossTerms` of one scene from its semantic vectors ``[N, S]``; with
    ``unlabelled_columns`` ``[U]`` (the unseen classes' rows of ``text_embeddings``) the unlabelled Gaussians and
    covered pixels take the partial-label term.

    ``rows`` (:func:`needed_rows`): ``semantic`` is ``[R, S]``, the vectors of those rows only; the 3D term then
    covers ``sample.loss_rows`` and the pixels read their contributors through ``rows``. ``text_3d``: the 3D term
    (mean, count) already computed (:func:`batch_losses`' eager path), used as is."""
    device = semantic.device
    temperature, unlabelled_weight = config.loss.temperature, config.loss.unlabelled_weight
    labels = sample.labels.to(device)
    pixel_ids = sample.pixel_ids.to(device)
    semantic_3d, loss_rows = semantic, None
    if rows is not None:  # without a subset of its own, a scene's rows are all of it (batch_losses)
        position = torch.full((labels.shape[0],), -1, dtype=torch.int64, device=device)
        position[rows.to(device)] = torch.arange(rows.shape[0], device=device)
        pixel_ids = torch.where(pixel_ids >= 0, position[pixel_ids.clamp_min(0)], -1)
        if sample.loss_rows is not None:
            loss_rows = sample.loss_rows.to(device)
            semantic_3d, labels = semantic[position[loss_rows]], labels[loss_rows]
    if text_3d is None and config.loss.no_3dt_align:
        text_3d = (semantic.sum() * 0.0, 0)
    elif text_3d is None:
        semantic3, labels3 = semantic_3d, labels  # transductive: every Gaussian takes a term
        weights3 = scene_row_weights(sample, config, unlabelled_columns is not None)  # only when the term is computed
        if weights3 is not None:
            weights3 = weights3.to(device) if loss_rows is None else weights3.to(device)[loss_rows]
        if unlabelled_columns is None:
            labelled = labels != IGNORE_LABEL
            semantic3, labels3 = semantic_3d[labelled], labels[labelled]
            weights3 = None if weights3 is None else weights3[labelled]
        if config.loss.lovasz_weight > 0:
            text_3d = text_and_lovasz_3d(net.phi, semantic3, labels3, text_embeddings, temperature,
                                         config.loss.lovasz_weight, class_weights, unlabelled_columns,
                                         unlabelled_weight, weights3)
        else:
            text_3d = text_cross_entropy_3d(net.phi, semantic3, labels3, text_embeddings, temperature, class_weights,
                                            unlabelled_columns, unlabelled_weight, weights3)
    pixel_weights = sample.pixel_weights.to(device)
    rendered = render_pixels(pixel_ids, pixel_weights, semantic)  # [P, S]
    pixel_labels = sample.pixel_labels.to(device)
    covered = (pixel_weights * (pixel_ids >= 0)).sum(-1) >= COVERAGE_MIN
    rows2 = pixel_labels != IGNORE_LABEL
    if unlabelled_columns is not None:
        rows2 = rows2 | covered
    logits2 = compute_text_logits(net.phi(rendered[rows2]), text_embeddings, temperature)
    text_2d = text_cross_entropy(logits2, pixel_labels[rows2], class_weights, unlabelled_columns, unlabelled_weight)
    cosine = None
    if use_teacher and sample.teacher is not None:
        predicted = net.psi(rendered[covered])
        cosine = masked_cosine_loss(predicted, sample.teacher.to(device)[covered],
                                    torch.ones(predicted.shape[0], dtype=torch.bool, device=device))
    return combine_losses(text_3d, text_2d, cosine, no_3dt_align=config.loss.no_3dt_align,
                          no_vs_align=config.loss.no_vs_align, cosine_weight=config.loss.cosine_weight)


def scene_row_weights(sample: SceneSample, config: TrainConfig, transductive: bool) -> "torch.Tensor | None":
    """``[N]`` weights of a scene's 3D-to-text terms (``LossConfig.opacity_power``; mean 1 over the Gaussians the
    term counts: the labelled ones, or every one in a transductive run), or None when every weight is 1 by
    configuration (power 0)."""
    power = config.loss.opacity_power
    if power == 0:
        return None
    counted = torch.ones_like(sample.labels, dtype=torch.bool) if transductive else sample.labels != IGNORE_LABEL
    return opacity_row_weights(sample.opacity_logits, counted, power)


def batch_losses(net, samples: Sequence[SceneSample], text_embeddings, config: TrainConfig, use_teacher: bool,
                 device, class_weights: "torch.Tensor | None" = None,
                 unlabelled_columns: "torch.Tensor | None" = None) -> list:
    """LossTerms of each scene of this process's slice (one network forward for all of them; with 3D-loss subsets,
    ``DataConfig.loss_gaussians``, the per-Gaussian stages run on :func:`needed_rows` only)."""
    means, attributes, batch_index = network_inputs(samples, device)
    scene_rows = [needed_rows(sample) for sample in samples]
    if all(rows is None for rows in scene_rows) and _eager_text_3d(net, config, text_embeddings, means, attributes):
        return _eager_batch_losses(net, samples, means, attributes, batch_index, text_embeddings, config, use_teacher,
                                   class_weights, unlabelled_columns)
    if all(rows is None for rows in scene_rows):
        semantic, counts = net(means, attributes, batch_index), [len(sample.means) for sample in samples]
    else:
        scene_rows = [torch.arange(len(s.means)) if rows is None else rows for s, rows in zip(samples, scene_rows)]
        wanted = batch_rows(samples, scene_rows).to(device)
        semantic, counts = net(means, attributes, batch_index, rows=wanted), [len(r) for r in scene_rows]
    # torch.split, not slicing: each slice's gradient would be a zero-filled copy of the whole batch (SliceBackward)
    return [scene_losses(net, scene_semantic, sample, text_embeddings, config, use_teacher, class_weights,
                         unlabelled_columns, rows)
            for sample, rows, scene_semantic in zip(samples, scene_rows, torch.split(semantic, counts))]


def _eager_text_3d(net, config: TrainConfig, text_embeddings: "torch.Tensor", means: "torch.Tensor",
                   attributes: "torch.Tensor") -> bool:
    """Whether :func:`batch_losses` takes the eager path (``ovgaussian.train.eager_adapter``): gradients recorded
    (for the network, not for the Gaussians' attributes), more rows than ``model.CHECKPOINT_MIN_ROWS`` (where the
    adapter would be checkpointed), an adapter, a 3D text term that is a sum over rows (no Lovasz) and the Gram-form
    decoder."""
    return (torch.is_grad_enabled() and means.shape[0] > model.CHECKPOINT_MIN_ROWS and net.config.use_adapter
            and not (means.requires_grad or attributes.requires_grad)
            and not config.loss.no_3dt_align and config.loss.lovasz_weight == 0
            and is_gram_decoder(net.phi))


def _eager_batch_losses(net, samples, means, attributes, batch_index, text_embeddings, config: TrainConfig,
                        use_teacher: bool, class_weights, unlabelled_columns) -> list:
    """:func:`batch_losses` with the adapter and the 3D text cross-entropy in one pass over row chunks, each chunk's
    gradients taken in its forward (``ovgaussian.train.eager_adapter``); the same terms as the one-piece path."""
    temperature, unlabelled_weight = config.loss.temperature, config.loss.unlabelled_weight
    labels = torch.cat([s.labels for s in samples]).to(means.device)
    row_tensors = (labels,)
    if config.loss.opacity_power != 0:
        weights = [scene_row_weights(s, config, unlabelled_columns is not None) for s in samples]
        row_tensors = (labels, torch.cat(weights).to(means.device))

    def row_loss(rows_semantic, rows_labels, *rest):
        rows_weights, terms = (None, rest) if len(row_tensors) == 1 else (rest[0], rest[1:])
        if unlabelled_columns is None:  # the labelled rows only, as scene_losses' semantic_3d[labelled]
            keep = rows_labels != IGNORE_LABEL
            rows_semantic, rows_labels = rows_semantic[keep], rows_labels[keep]
            rows_weights = None if rows_weights is None else rows_weights[keep]
        logits = gram_text_logits(rows_semantic, GramTerms(*terms), temperature)
        return text_sum(logits, rows_labels, class_weights, unlabelled_columns, unlabelled_weight, rows_weights)

    scene_rows, rows = [None] * len(samples), None  # transductive: every Gaussian takes a 3D term
    if unlabelled_columns is None:
        scene_rows = [term_rows(s) for s in samples]
        rows = batch_rows(samples, scene_rows).to(means.device)
    semantic, sums = semantic_with_row_loss(net, means, attributes, batch_index, len(samples), row_loss, row_tensors,
                                            tuple(gram_terms(net.phi, text_embeddings)), rows=rows)
    counts = [len(s.means) if r is None else len(r) for s, r in zip(samples, scene_rows)]
    terms = []
    for b, (sample, scene_semantic) in enumerate(zip(samples, torch.split(semantic, counts))):
        count = text_3d_count(sample.labels, unlabelled_columns)
        text_3d = (sums[b] * 0.0, 0) if count == 0 else (sums[b] / count, count)
        terms.append(scene_losses(net, scene_semantic, sample, text_embeddings, config, use_teacher, class_weights,
                                  unlabelled_columns, scene_rows[b], text_3d))
    return terms


def batch_rows(samples: Sequence[SceneSample], scene_rows: Sequence["torch.Tensor"]) -> "torch.Tensor":
    """``[R]`` rows of the concatenated batch (:func:`network_inputs`) from each scene's own increasing rows."""
    starts = torch.tensor([0] + [len(s.means) for s in samples]).cumsum(0).tolist()
    return torch.cat([rows + start for rows, start in zip(scene_rows, starts)])


def term_rows(sample: SceneSample) -> "torch.Tensor":
    """``[R]`` increasing rows of the Gaussians that take part in a step's losses without a transductive term: the
    labelled ones (3D text term) and every contributor of the sampled pixels (2D terms). The others' semantic vectors
    are read by no loss, so the eager path (``_eager_batch_losses``) does not compute them."""
    labelled = sample.labels != IGNORE_LABEL
    labelled[sample.pixel_ids[sample.pixel_ids >= 0]] = True
    return torch.nonzero(labelled)[:, 0]
