"""Generative zero-shot feature synthesis (ZS3Net, Bucher et al. 2019; 3DGenZ, Michele et al. 2021).

The classifier of a model trained on seen classes never predicts an unseen one. Here a generator learns,
on the seen classes, how a class's text embedding maps to the *distribution* of its features; it then
synthesizes features for the unseen classes from their text embeddings alone, and a softmax classifier is
retrained on real seen features plus synthetic unseen ones:

- features: the decoded, L2-normalized semantic vectors ``phi(s) / |phi(s)|`` of the trained model (the space
  its text scores live in), standardized per dimension with the real features' statistics;
- generator: ``G(text, z) = MLP([text, z])``, ``z ~ N(0, I)``, trained as a GMMN: the sum over seen classes of
  the squared MMD between generated and real features under a mixture of Gaussian kernels;
- classifier: linear softmax over all K classes, full-batch Adam, each class weighted equally.

Real features come from the train split through the training vocabulary (no unseen class in it), so no
unseen-class label is read.
"""

from __future__ import annotations

from typing import Iterable, NamedTuple, Sequence

import numpy as np
import torch
from torch import Tensor, nn

from ovgaussian.openvocab.config import SynthesisConfig
from ovgaussian.text.vocabulary import Vocabulary, map_labels
from seggaussian.core.constants import IGNORE_LABEL
from seggaussian.util.seeds import scene_seed

#: Lower bound of a feature dimension's standard deviation (a constant dimension is not divided by 0).
STD_EPS = 1e-6


class Standardizer(NamedTuple):
    """Per-dimension mean ``[F]`` and standard deviation ``[F]`` of the real features."""

    mean: Tensor
    std: Tensor

    def apply(self, x: Tensor) -> Tensor:
        return (x - self.mean) / self.std

    def invert(self, x: Tensor) -> Tensor:
        return x * self.std + self.mean


def standardizer(features: Tensor) -> Standardizer:
    return Standardizer(features.mean(0), features.std(0).clamp_min(STD_EPS))


#: Floor of a Gaussian kernel's exponent: exp(-80) is 1.8e-35, so a kernel value below it changes an MMD (a mean
#: of values in [0, len(bandwidths)]) by less than float32 resolves, and its gradient is as small. Without the floor,
#: the far pairs of standardized 384-wide features (exponents to -6,000) send every exp down the slow underflow
#: path: 15-20x the cost of an ordinary exp on this CPU.
EXPONENT_FLOOR = -80.0


def _mean_kernel(p: Tensor, q: Tensor, bandwidths: Sequence[float]) -> Tensor:
    """Mean over sample pairs of the summed Gaussian kernels of ``p`` ``[..., A, F]`` and ``q`` ``[..., B, F]``."""
    # squared distances in Gram form, about the samples' own mean: an offset shared by the samples would otherwise
    # cancel catastrophically in float32 (distances do not depend on the centre, so it needs no gradient). A far
    # outlier still pulls the mean: its set's small distances then carry float32 error ~ eps * offset^2 (a median
    # would not, at 17 ms a call against the whole step's 70)
    centre = torch.cat([p, q], dim=-2).detach().mean(-2, keepdim=True)
    p, q = p - centre, q - centre
    d2 = (p.square().sum(-1).unsqueeze(-1) + q.square().sum(-1).unsqueeze(-2)
          - 2.0 * p @ q.transpose(-1, -2)).clamp_min(0.0)  # [..., A, B]
    k = sum(torch.exp((d2 * (-0.5 / (h * h))).clamp_min(EXPONENT_FLOOR)) for h in bandwidths)
    return k.mean((-1, -2))


def mmd2(x: Tensor, y: Tensor, bandwidths: Sequence[float]) -> Tensor:
    """Biased squared MMD of samples ``x`` ``[..., A, F]`` and ``y`` ``[..., B, F]`` under a sum of Gaussian
    kernels; leading dimensions are a batch of independent pairs (result ``[...]``)."""
    return (_mean_kernel(x, x, bandwidths) + _mean_kernel(y, y, bandwidths)
            - 2.0 * _mean_kernel(x, y, bandwidths))


def mmd2_reference(x: Tensor, y: Tensor, bandwidths: Sequence[float]) -> Tensor:
    """:func:`mmd2` of one pair, term by term over sample pairs in float64 (the slow, obviously correct form)."""
    x, y = x.double(), y.double()

    def mean_kernel(p: Tensor, q: Tensor) -> Tensor:
        total = torch.zeros((), dtype=torch.float64)
        for i in range(p.shape[0]):
            d2 = (p[i] - q).square().sum(-1)  # [len(q)]
            total = total + sum(torch.exp(-d2 / (2.0 * h * h)) for h in bandwidths).sum()
        return total / (p.shape[0] * q.shape[0])

    return mean_kernel(x, x) + mean_kernel(y, y) - 2.0 * mean_kernel(x, y)


class FeatureGenerator(nn.Module):
    """``(text [C, E], count) -> [C * count, F]`` features (standardized units), one MLP with noise input."""

    def __init__(self, text_width: int, feature_width: int, config: SynthesisConfig) -> None:
        super().__init__()
        self.noise_width = config.noise_width
        self.net = nn.Sequential(nn.Linear(text_width + config.noise_width, config.hidden_width), nn.LeakyReLU(0.2),
                                 nn.Linear(config.hidden_width, feature_width))

    def forward(self, text: Tensor, count: int, generator: torch.Generator) -> Tensor:
        cond = text.repeat_interleave(count, dim=0)
        noise = torch.randn(cond.shape[0], self.noise_width, generator=generator)
        return self.net(torch.cat([cond, noise], dim=1))


def train_generator(text: Tensor, features: Tensor, labels: Tensor, config: SynthesisConfig
                    ) -> tuple[FeatureGenerator, Standardizer]:
    """Generator of features given a class's text embedding, fitted on ``features`` ``[M, F]`` with ``labels``
    ``[M]`` in ``0..C-1`` (the rows of ``text`` ``[C, E]``)."""
    g = torch.Generator().manual_seed(config.seed)
    torch.manual_seed(config.seed)  # nn.Linear initialization
    scale = standardizer(features)
    z = scale.apply(features)
    classes = [c for c in range(text.shape[0]) if bool((labels == c).any())]
    if not classes:
        raise ValueError("feature synthesis: no real features of a seen class")
    rows = {c: torch.nonzero(labels == c)[:, 0] for c in classes}
    gen = FeatureGenerator(text.shape[1], features.shape[1], config)
    optimizer = torch.optim.Adam(gen.parameters(), lr=config.learning_rate)
    n = config.samples_per_class
    for _ in range(config.generator_steps):
        pick = torch.randperm(len(classes), generator=g)[: config.classes_per_step].tolist()
        batch = [classes[i] for i in pick]
        fake = gen(text[batch], n, g)  # [len(batch) * n, F], class by class
        real = torch.stack([z[rows[c][torch.randint(rows[c].numel(), (n,), generator=g)]] for c in batch])
        loss = mmd2(fake.reshape(len(batch), n, -1), real, config.kernel_bandwidths).sum()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    return gen.eval(), scale


def synthesize(gen: FeatureGenerator, scale: Standardizer, text: Tensor, count: int, seed: int) -> Tensor:
    """``[U * count, F]`` features of the classes of ``text`` ``[U, E]`` (in the real features' units)."""
    with torch.no_grad():
        return scale.invert(gen(text, count, torch.Generator().manual_seed(seed)))


class LinearClassifier(NamedTuple):
    """Softmax classifier over standardized features: ``logits = standardize(x) W^T + b``."""

    weight: Tensor  # [K, F]
    bias: Tensor  # [K]
    scale: Standardizer

    def logits(self, features: Tensor) -> Tensor:
        return self.scale.apply(features) @ self.weight.T + self.bias


def train_classifier(features: Tensor, labels: Tensor, num_classes: int, config: SynthesisConfig) -> LinearClassifier:
    """Class-balanced softmax regression on ``features`` ``[M, F]`` with ``labels`` ``[M]`` in ``0..K-1``."""
    torch.manual_seed(config.seed)
    scale = standardizer(features)
    x = scale.apply(features)
    counts = torch.bincount(labels, minlength=num_classes).float()
    class_weight = torch.where(counts > 0, counts.sum() / (num_classes * counts.clamp_min(1)), torch.zeros(()))
    weight = torch.zeros(num_classes, x.shape[1], requires_grad=True)
    bias = torch.zeros(num_classes, requires_grad=True)
    optimizer = torch.optim.Adam([weight, bias], lr=10 * config.learning_rate)
    for _ in range(config.classifier_steps):
        loss = nn.functional.cross_entropy(x @ weight.T + bias, labels, weight=class_weight)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    return LinearClassifier(weight.detach(), bias.detach(), scale)


def real_features(predictor, scenes: Iterable, vocabulary: Vocabulary, per_class: int, seed: int):
    """(features ``[M, F]``, labels ``[M]`` indices into ``vocabulary``) of the scenes' Gaussians, at most
    ``per_class`` per class (seeded reservoir by random keys). Labels outside ``vocabulary`` are IGNORE, unread."""
    feats, labs, keys = [], [], []
    for scene in scenes:
        labels = map_labels(scene.gaussians.extras["semantic"], vocabulary)
        keep = np.flatnonzero(labels != IGNORE_LABEL)
        if keep.size == 0:
            continue
        rng = np.random.default_rng(scene_seed(seed, scene.scene_id))
        vectors = predictor.encode(scene)[keep]
        feats.append(predictor.decode(vectors))
        labs.append(labels[keep])
        keys.append(rng.random(keep.size))
    if not feats:
        raise ValueError("feature synthesis: no labelled Gaussian of a seen class in the train split")
    feats, labs, keys = np.concatenate(feats), np.concatenate(labs), np.concatenate(keys)
    chosen = []
    for c in np.unique(labs):
        rows = np.flatnonzero(labs == c)
        chosen.append(rows[np.argsort(keys[rows], kind="stable")[:per_class]])
    chosen = np.sort(np.concatenate(chosen))
    return torch.from_numpy(feats[chosen]).float(), torch.from_numpy(labs[chosen]).long()


class GenerativePredictor:
    """The model's features scored by the classifier retrained with synthetic unseen features."""

    name = "model+generative"

    def __init__(self, inner, classifier: LinearClassifier, class_ids: np.ndarray) -> None:
        self.inner = inner
        self.classifier = classifier
        self.columns = {int(c): i for i, c in enumerate(class_ids)}

    def encode(self, scene) -> np.ndarray:
        return self.inner.encode(scene)

    def classify(self, vectors: np.ndarray, class_ids: np.ndarray) -> np.ndarray:
        missing = [int(c) for c in class_ids if int(c) not in self.columns]
        if missing:
            raise ValueError(f"generative classifier: classes {missing} were not in its vocabulary")
        features = torch.from_numpy(self.inner.decode(vectors)).float()
        with torch.no_grad():
            logits = self.classifier.logits(features)
        return logits[:, [self.columns[int(c)] for c in class_ids]].numpy()


def fit_generative_predictor(predictor, scenes: Iterable, vocabulary: Vocabulary, seen_vocabulary: Vocabulary,
                             config: SynthesisConfig) -> tuple[GenerativePredictor, dict]:
    """The generative method on ``predictor`` (a ModelPredictor: ``encode``, ``decode``, ``text_embeddings``):
    real seen features of ``scenes`` (train split) -> generator -> synthetic unseen -> classifier over
    ``vocabulary``. Returns the predictor and a JSON-ready record of what was fitted."""
    feats, seen_labels = real_features(predictor, scenes, seen_vocabulary, config.real_per_class, config.seed)
    text_all = predictor.text_embeddings(list(vocabulary.names)).float().cpu()  # [K, E]
    seen_cols = torch.tensor([vocabulary.names.index(n) for n in seen_vocabulary.names])
    gen, scale = train_generator(text_all[seen_cols], feats, seen_labels, config)
    unseen = [i for i, n in enumerate(vocabulary.names) if n not in seen_vocabulary.names]
    synthetic = synthesize(gen, scale, text_all[unseen], config.synthetic_per_class, config.seed + 1)
    labels = torch.cat([seen_cols[seen_labels], torch.tensor(unseen).repeat_interleave(config.synthetic_per_class)])
    classifier = train_classifier(torch.cat([feats, synthetic]), labels, len(vocabulary.names), config)
    record = {"real_features": int(feats.shape[0]), "seen_classes": list(seen_vocabulary.names),
              "synthesized_classes": [vocabulary.names[i] for i in unseen],
              "synthetic_per_class": config.synthetic_per_class, "split": "train"}
    return GenerativePredictor(predictor, classifier, vocabulary.class_ids), record
