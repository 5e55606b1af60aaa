"""The scene's language field as the viewer queries it: per-Gaussian vectors decoded once, scores cached per text.

A trained run gives each Gaussian a semantic vector ``s`` (``ModelPredictor.encode_gaussians``); its language
vector is ``phi(s)`` L2-normalized (``ModelPredictor.decode``), and the score of a text is the cosine with the
text's embedding (``ModelPredictor.text_embeddings``): the same three calls ``ovgaussian predict`` and
``ovgaussian bench`` use. :class:`QueryField` decodes every Gaussian once (``[N, D]`` float32 kept in memory) and
keeps the ``[N]`` score column of every query (and of the canonical negatives), so a query costs one text
embedding and one ``[N, D] x [D]`` product, and moving the threshold or switching modes costs no scoring.
"""

from __future__ import annotations

import threading
from typing import Callable, Sequence

import numpy as np

#: Gaussians decoded at once when the field is built (bounds the ``[rows, D]`` float32 temporaries).
DECODE_CHUNK_ROWS = 65536


class QueryField:
    """Cached language vectors and per-text score columns of one scene.

    Args:
        decoded: ``[N, D]`` float32 L2-normalized language vectors.
        embed: ``names -> [T, D]`` L2-normalized text embeddings of ``names`` (in order).
        trained_names: the class names the run was trained on (shown in the inspect panel).
    """

    def __init__(self, decoded: np.ndarray, embed: Callable[[Sequence[str]], np.ndarray],
                 trained_names: Sequence[str] = ()) -> None:
        decoded = np.ascontiguousarray(decoded, dtype=np.float32)
        if decoded.ndim != 2:
            raise ValueError(f"QueryField: decoded vectors must be [N, D], got {decoded.shape}")
        self.decoded = decoded
        self._embed = embed
        self.trained_names = tuple(trained_names)
        self._columns: dict[str, np.ndarray] = {}  # text -> [N] scores
        self._embeddings: dict[str, np.ndarray] = {}  # text -> [D] embedding
        self._labels: dict[tuple[str, ...], np.ndarray] = {}  # vocabulary -> [N] argmax
        self._lock = threading.Lock()

    @classmethod
    def from_predictor(cls, predictor, vectors: np.ndarray, chunk_rows: int = DECODE_CHUNK_ROWS) -> "QueryField":
        """The field of ``vectors`` (``[N, S]`` semantic vectors) decoded by a ``ModelPredictor`` (or any object with
        its ``decode`` and ``text_embeddings``)."""
        vectors = np.asarray(vectors)
        width = None
        parts = []
        for start in range(0, vectors.shape[0], chunk_rows):
            part = np.asarray(predictor.decode(vectors[start:start + chunk_rows]), dtype=np.float32)
            width = part.shape[1]
            parts.append(part)
        if not parts:  # an empty scene: the width of one decoded zero vector
            width = np.asarray(predictor.decode(np.zeros((1, vectors.shape[1]), np.float32))).shape[1]
        decoded = np.concatenate(parts) if parts else np.zeros((0, width), np.float32)

        def embed(names: Sequence[str]) -> np.ndarray:
            text = predictor.text_embeddings(tuple(names))
            text = text.detach().cpu().numpy() if hasattr(text, "detach") else np.asarray(text)
            return text.astype(np.float32, copy=False)

        return cls(decoded, embed, getattr(predictor, "trained_names", ()))

    def __len__(self) -> int:
        return self.decoded.shape[0]

    def embeddings(self, texts: Sequence[str]) -> np.ndarray:
        """``[T, D]`` float32 text embeddings (cached per text; the missing ones embedded in one call)."""
        texts = tuple(texts)
        with self._lock:
            missing = tuple(dict.fromkeys(t for t in texts if t not in self._embeddings))
            if missing:
                block = np.asarray(self._embed(missing), dtype=np.float32)
                if block.shape != (len(missing), self.decoded.shape[1]):
                    raise ValueError(f"text embeddings have shape {block.shape}, expected "
                                     f"({len(missing)}, {self.decoded.shape[1]}) (text encoder and run disagree)")
                for j, text in enumerate(missing):
                    self._embeddings[text] = block[j].copy()
            if not texts:
                return np.zeros((0, self.decoded.shape[1]), np.float32)
            return np.stack([self._embeddings[t] for t in texts])

    def scores(self, texts: Sequence[str]) -> np.ndarray:
        """``[N, T]`` float32 cosine scores of every Gaussian with each text (an ``[N]`` column cached per text:
        the queries and the negatives; a whole vocabulary goes through :meth:`argmax` instead)."""
        texts = tuple(texts)
        embeddings = self.embeddings(texts)
        with self._lock:
            missing = [j for j, t in enumerate(texts) if t not in self._columns]
            if missing:
                block = self.decoded @ embeddings[missing].T  # [N, M]
                for col, j in enumerate(missing):
                    self._columns[texts[j]] = np.ascontiguousarray(block[:, col])
            if not texts:
                return np.zeros((len(self), 0), np.float32)
            return np.stack([self._columns[t] for t in texts], axis=1)

    def argmax(self, texts: Sequence[str], chunk_rows: int = DECODE_CHUNK_ROWS) -> np.ndarray:
        """``[N]`` int32 index of the best-scoring text per Gaussian (chunked, cached per vocabulary)."""
        texts = tuple(texts)
        if not texts:
            raise ValueError("argmax: empty vocabulary")
        if texts in self._labels:
            return self._labels[texts]
        embeddings = self.embeddings(texts)
        out = np.empty(len(self), np.int32)
        for start in range(0, len(self), chunk_rows):
            out[start:start + chunk_rows] = np.argmax(self.decoded[start:start + chunk_rows] @ embeddings.T, axis=1)
        self._labels[texts] = out
        return out

    def gaussian_scores(self, index: int, texts: Sequence[str]) -> np.ndarray:
        """``[T]`` scores of one Gaussian."""
        return self.embeddings(texts) @ self.decoded[int(index)]
