"""Open-vocabulary relevancy and the viewer's colours: pure numpy, no viewer, no model.

Relevancy of a query (LERF, Kerr et al. 2023, section 3.4; used as is by LangSplat, Qin et al. 2024): with
``s_q`` the score (cosine) of a Gaussian's language vector with the query's text embedding and ``s_i`` its
scores with the canonical negatives ("object", "things", "stuff", "texture"),

    relevancy = min_i  exp(s_q) / (exp(s_i) + exp(s_q))

the pairwise softmax of the query against each negative, its worst case over the negatives. The pairwise
softmax is ``sigmoid(s_q - s_i)`` and the sigmoid is increasing, so the minimum is taken at the largest
negative score: ``relevancy = sigmoid(s_q - max_i s_i)`` (:func:`relevancy`; :func:`relevancy_reference` is the
formula as written, the test's slow reference). Relevancy lies in (0, 1); 0.5 means "as close to the query as to
the closest negative".

Several queries (``"chair, table"``) are compared by their relevancies: each Gaussian goes to the query of
highest relevancy, and is highlighted when that relevancy reaches the threshold (:func:`query_hits`).

The LERF relevancy needs a threshold per query: its pairwise softmax is taken on raw cosines, so every phrase sits
near 0.5 at its own offset, and 0.5 takes most of a room for every phrase. The viewer scores a query with its
**calibrated relevancy** instead (:func:`calibrated_relevancy`): the probability of the query in a softmax, at the
run's training temperature ``T`` (its logits were cosine / T), against the competitors: the run's vocabulary (the
query itself and its repeats left out) and the canonical negatives,

    calibrated = exp(s_q / T) / (exp(s_q / T) + sum_c exp(s_c / T)).

One threshold then means nearly the same for every phrase: at 0.5 the query is more likely than all its competitors
together. It is unchanged when the same constant is added to every score, never lowered by a higher query score,
and a competitor far below the query everywhere changes nothing (its term vanishes).

What is left between phrases is each class's own operating point (walls, which border doors and windows
everywhere, are best taken below 0.5; doors and monitors, which other things resemble, above). A run's
**relevancy calibration** (``ovgaussian.view.calibration``) fits one logit offset ``d_q`` per name of its
vocabulary on the train split's rooms; the query's logit is lowered by it,

    calibrated = exp(s_q / T - d_q) / (exp(s_q / T - d_q) + sum_c exp(s_c / T)),

so that 0.5 falls where the softmax probability equals ``sigmoid(d_q)``, the threshold of best IoU on the train
rooms. Names without an offset (outside the vocabulary, or too rare in the train rooms) keep ``d_q = 0``.
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np

#: LERF's canonical negative phrases (Kerr et al. 2023, section 3.4).
CANONICAL_NEGATIVES = ("object", "things", "stuff", "texture")
#: Default highlight threshold on the calibrated relevancy: the query more likely than all its competitors together,
#: at the operating point its offset sets (measured against the per-query best threshold:
#: benchmarks/relevancy_threshold.py, results/relevancy.md).
DEFAULT_THRESHOLD = 0.5
#: Softmax temperature of the calibrated relevancy when the run records none: ``ovgaussian train``'s default loss
#: temperature (``LossConfig.temperature``), the scale the scores were trained at.
DEFAULT_TEMPERATURE = 0.07
#: Gaussians scored at once by :func:`calibrated_relevancy` (bounds its ``[rows, C]`` temporaries).
CALIBRATION_CHUNK_ROWS = 262144

#: Colour of the least relevant highlighted Gaussian (relevancy at the threshold), RGB in [0, 1]: yellow.
HIGHLIGHT_LOW_RGB = (1.0, 0.85, 0.0)
#: Colour of the most relevant highlighted Gaussian (the query's largest relevancy), RGB in [0, 1]: red.
HIGHLIGHT_HIGH_RGB = (1.0, 0.0, 0.0)
#: Brightness kept by a Gaussian below the threshold: its scene colour turned grey and scaled by this, so the
#: highlighted ones stand out and the room stays legible.
DIM_FACTOR = 0.45
#: Rec. 601 luma weights (R, G, B) of the grey a dimmed Gaussian gets.
LUMA_WEIGHTS = (0.299, 0.587, 0.114)
#: Smallest relevancy span mapped onto the highlight ramp (all hits equal: they take the high colour).
MIN_RAMP_SPAN = 1e-6


def parse_queries(text: str) -> tuple[str, ...]:
    """``" chair,  table ,, chair"`` -> ``("chair", "table")``: comma-separated, whitespace collapsed, empty and
    repeated (case-insensitive) entries dropped; ``()`` for a blank text."""
    out: list[str] = []
    seen: set[str] = set()
    for part in text.split(","):
        name = " ".join(part.split())
        if name and name.lower() not in seen:
            seen.add(name.lower())
            out.append(name)
    return tuple(out)


def relevancy(query_scores: np.ndarray, negative_scores: np.ndarray) -> np.ndarray:
    """LERF relevancy ``sigmoid(s_q - max_i s_i)``.

    Args:
        query_scores: ``[N]`` or ``[N, Q]`` scores of the queries.
        negative_scores: ``[N, K]`` scores of the canonical negatives (K >= 1).

    Returns:
        float32, the shape of ``query_scores``, in (0, 1).
    """
    q = np.asarray(query_scores, dtype=np.float32)
    neg = np.asarray(negative_scores, dtype=np.float32)
    if neg.ndim != 2 or neg.shape[1] == 0 or neg.shape[0] != q.shape[0]:
        raise ValueError(f"relevancy: negative scores must be [N, K>=1] with N = {q.shape[0]}, got {neg.shape}")
    top = neg.max(axis=1)
    diff = q - (top[:, None] if q.ndim == 2 else top)
    # sigmoid(x) = 0.5 * (1 + tanh(x / 2)): no overflow for any finite x
    out = np.tanh(0.5 * diff)
    out += 1.0
    out *= 0.5
    return out.astype(np.float32, copy=False)


def relevancy_reference(query_scores: np.ndarray, negative_scores: np.ndarray) -> np.ndarray:
    """The relevancy formula as LERF writes it, one Gaussian, query and negative at a time (tests only)."""
    q = np.asarray(query_scores, dtype=np.float64)
    squeeze = q.ndim == 1
    q = q[:, None] if squeeze else q
    neg = np.asarray(negative_scores, dtype=np.float64)
    out = np.empty(q.shape)
    for n in range(q.shape[0]):
        for j in range(q.shape[1]):
            out[n, j] = min(np.exp(q[n, j]) / (np.exp(neg[n, i]) + np.exp(q[n, j])) for i in range(neg.shape[1]))
    return out[:, 0] if squeeze else out


def phrase_key(text: str) -> str:
    """What makes two phrases the same: case and repeated whitespace ignored."""
    return " ".join(text.split()).lower()


def competitor_mask(queries: Sequence[str], competitors: Sequence[str]) -> np.ndarray:
    """``[Q, C]`` bool: competitor ``c`` counts against query ``q`` unless it is the same phrase (``phrase_key``),
    so a query in the vocabulary is not its own competitor."""
    return np.array([[phrase_key(c) != phrase_key(q) for c in competitors] for q in queries], dtype=bool).reshape(
        len(queries), len(competitors))


def query_offsets(queries: Sequence[str], offsets: dict[str, float] | None) -> np.ndarray:
    """``[Q]`` float32 logit offsets of ``queries`` from ``{name: offset}`` (matched by ``phrase_key``); 0 for a
    phrase without one."""
    table = {phrase_key(name): float(value) for name, value in (offsets or {}).items()}
    return np.array([table.get(phrase_key(q), 0.0) for q in queries], np.float32)


def competitors_of(vocabulary: Sequence[str], negatives: Sequence[str]) -> tuple[str, ...]:
    """The competitors of every query: the vocabulary, then the negatives, repeats dropped (first kept)."""
    return tuple(dict.fromkeys(tuple(vocabulary) + tuple(negatives)))


def calibrated_relevancy(query_scores: np.ndarray, competitor_scores: np.ndarray, mask: np.ndarray | None = None,
                         temperature: float = DEFAULT_TEMPERATURE, offsets: np.ndarray | None = None,
                         chunk_rows: int = CALIBRATION_CHUNK_ROWS) -> np.ndarray:
    """The probability of each query against its competitors, softmax of ``scores / temperature`` with each query's
    logit lowered by its offset.

    Args:
        query_scores: ``[N]`` or ``[N, Q]`` scores of the queries.
        competitor_scores: ``[N, C]`` scores of the competitors (vocabulary and canonical negatives).
        mask: ``[Q, C]`` bool, the competitors each query is compared with (:func:`competitor_mask`); None: all.
        temperature: softmax temperature (> 0).
        offsets: ``[Q]`` finite logit offsets ``d_q`` (module docstring); None: all 0.

    Returns:
        float32, the shape of ``query_scores``, in [0, 1].
    """
    q = np.asarray(query_scores, dtype=np.float32)
    squeeze = q.ndim == 1
    q = q[:, None] if squeeze else q
    comp = np.asarray(competitor_scores, dtype=np.float32)
    if comp.ndim != 2 or comp.shape[0] != q.shape[0]:
        raise ValueError(f"calibrated relevancy: competitor scores must be [N, C] with N = {q.shape[0]}, "
                         f"got {comp.shape}")
    if not temperature > 0:
        raise ValueError(f"calibrated relevancy: temperature must be > 0, got {temperature}")
    mask = np.ones((q.shape[1], comp.shape[1]), bool) if mask is None else np.asarray(mask, bool)
    if mask.shape != (q.shape[1], comp.shape[1]):
        raise ValueError(f"calibrated relevancy: mask must be [Q, C] = {(q.shape[1], comp.shape[1])}, got {mask.shape}")
    shift = np.zeros(q.shape[1], np.float32) if offsets is None else np.asarray(offsets, np.float32).reshape(-1)
    if shift.shape != (q.shape[1],) or not np.isfinite(shift).all():
        raise ValueError(f"calibrated relevancy: offsets must be {q.shape[1]} finite numbers, got {offsets}")
    inv = np.float32(1.0 / temperature)
    out = np.empty(q.shape, np.float32)
    for j in range(q.shape[1]):
        cols = np.flatnonzero(mask[j])
        if not len(cols):  # no competitor: the query wins everywhere
            out[:, j] = 1.0
            continue
        for start in range(0, q.shape[0], chunk_rows):  # a chunk of rows at a time: memory bounded
            sq = q[start:start + chunk_rows, j]
            # 1 / (1 + sum_c exp((s_c - s_q) / T + d_q)), its largest exponent subtracted: no overflow
            diff = (comp[start:start + chunk_rows, cols] - sq[:, None]) * inv + shift[j]  # [rows, C]
            top = np.maximum(diff.max(axis=1), 0.0)
            total = np.exp(-top) + np.exp(diff - top[:, None]).sum(axis=1)
            out[start:start + chunk_rows, j] = np.exp(-top) / total
    return out[:, 0] if squeeze else out


def calibrated_relevancy_reference(query_scores: np.ndarray, competitor_scores: np.ndarray,
                                   mask: np.ndarray | None = None, temperature: float = DEFAULT_TEMPERATURE,
                                   offsets: np.ndarray | None = None) -> np.ndarray:
    """The softmax as written, one Gaussian and query at a time, in float64 (tests only)."""
    q = np.asarray(query_scores, dtype=np.float64)
    squeeze = q.ndim == 1
    q = q[:, None] if squeeze else q
    comp = np.asarray(competitor_scores, dtype=np.float64)
    mask = np.ones((q.shape[1], comp.shape[1]), bool) if mask is None else np.asarray(mask, bool)
    shift = [0.0] * q.shape[1] if offsets is None else [float(v) for v in np.asarray(offsets).reshape(-1)]
    out = np.empty(q.shape)
    for n in range(q.shape[0]):
        for j in range(q.shape[1]):
            logits = [q[n, j] / temperature - shift[j]] + [comp[n, c] / temperature for c in range(comp.shape[1])
                                                           if mask[j, c]]
            top = max(logits)
            out[n, j] = np.exp(logits[0] - top) / sum(np.exp(v - top) for v in logits)
    return out[:, 0] if squeeze else out


class QueryHits(NamedTuple):
    """Per Gaussian, the answer to one or several queries.

    Fields:
        best: ``[N]`` int64 index of the query of highest relevancy.
        value: ``[N]`` float32 that relevancy.
        hit: ``[N]`` bool, ``value >= threshold``.
    """

    best: np.ndarray
    value: np.ndarray
    hit: np.ndarray


def query_hits(relevancies: np.ndarray, threshold: float) -> QueryHits:
    """``[N]`` or ``[N, Q]`` relevancies -> the winning query per Gaussian and whether it reaches ``threshold``."""
    r = np.asarray(relevancies, dtype=np.float32)
    if r.ndim == 1:
        r = r[:, None]
    if r.shape[1] == 1:
        best = np.zeros(r.shape[0], np.int64)
        value = r[:, 0]
    else:
        best = np.argmax(r, axis=1)
        value = np.take_along_axis(r, best[:, None], axis=1)[:, 0]
    return QueryHits(best, value, value >= np.float32(threshold))


def dimmed_colours(rgb: np.ndarray) -> np.ndarray:
    """``[N, 3]`` uint8 scene colours -> grey, darkened by ``DIM_FACTOR`` (uint8)."""
    luma = np.asarray(rgb, dtype=np.float32) @ np.asarray(LUMA_WEIGHTS, np.float32)
    grey = np.clip(luma * np.float32(DIM_FACTOR), 0, 255).astype(np.uint8)
    return np.repeat(grey[:, None], 3, axis=1)


def query_colours(dimmed: np.ndarray, hits: QueryHits, query_rgb: np.ndarray | None = None) -> np.ndarray:
    """``[N, 3]`` uint8 colours of a query answer.

    Gaussians below the threshold keep ``dimmed`` (:func:`dimmed_colours` of the scene). With one query, a hit is
    coloured on the ramp ``HIGHLIGHT_LOW_RGB`` (relevancy at the threshold) -> ``HIGHLIGHT_HIGH_RGB`` (the largest
    relevancy); with several, a hit takes its query's colour ``query_rgb[best]`` (``[Q, 3]`` uint8).
    """
    out = np.array(dimmed, dtype=np.uint8, copy=True)
    index = np.flatnonzero(hits.hit)
    if index.size == 0:
        return out
    if query_rgb is not None and len(query_rgb) > 1:
        out[index] = np.asarray(query_rgb, np.uint8)[hits.best[index]]
        return out
    values = hits.value[index]
    low = float(values.min())
    span = float(values.max()) - low
    if span < MIN_RAMP_SPAN:  # every hit equally relevant: all take the high colour
        t = np.ones((index.size, 1), np.float32)
    else:
        t = ((values - np.float32(low)) / np.float32(span))[:, None]
    lo = np.asarray(HIGHLIGHT_LOW_RGB, np.float32) * np.float32(255)
    hi = np.asarray(HIGHLIGHT_HIGH_RGB, np.float32) * np.float32(255)
    out[index] = np.clip(np.rint(lo + t * (hi - lo)), 0, 255).astype(np.uint8)
    return out


def top_k(scores: np.ndarray, names: Sequence[str], k: int) -> list[tuple[str, float]]:
    """The ``k`` highest of one Gaussian's ``[C]`` scores as ``(name, score)``, best first."""
    scores = np.asarray(scores, dtype=np.float64)
    order = np.argsort(-scores, kind="stable")[:k]
    return [(names[int(i)], float(scores[int(i)])) for i in order]
