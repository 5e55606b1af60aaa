"""Text encoders: the bundled MiniLM, a tiny local CLIP, prompts, caching and clear errors."""

from __future__ import annotations

import json
import string
from pathlib import Path

import pytest
import torch

from ovgaussian.text import encoders as T
from ovgaussian.run.config import TextConfig

NAMES = ["chair", "table", "sofa"]


def write_tiny_clip(folder: Path, projection_dim: int = 24) -> Path:
    """A randomly initialized CLIP with a character-level BPE vocabulary, saved as a local model folder."""
    from transformers import CLIPConfig, CLIPModel, CLIPTokenizer

    symbols = list(string.ascii_lowercase) + ["."]
    vocab = {"<|startoftext|>": 0, "<|endoftext|>": 1}
    for s in symbols:
        vocab[s] = len(vocab)
        vocab[s + "</w>"] = len(vocab)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "vocab.json").write_text(json.dumps(vocab))
    (folder / "merges.txt").write_text("#version: 0.2\n")
    tokenizer = CLIPTokenizer(str(folder / "vocab.json"), str(folder / "merges.txt"))
    tokenizer.save_pretrained(str(folder))
    config = CLIPConfig(
        text_config=dict(hidden_size=32, intermediate_size=48, num_hidden_layers=2, num_attention_heads=2,
                         vocab_size=len(vocab), max_position_embeddings=40, bos_token_id=0, eos_token_id=1,
                         pad_token_id=1),
        vision_config=dict(hidden_size=32, intermediate_size=48, num_hidden_layers=2, num_attention_heads=2,
                           image_size=32, patch_size=8),
        projection_dim=projection_dim,
    )
    torch.manual_seed(0)
    CLIPModel(config).save_pretrained(str(folder))
    return folder


@pytest.fixture(scope="module")
def tiny_clip(tmp_path_factory):
    return write_tiny_clip(tmp_path_factory.mktemp("clip"))


@pytest.fixture(scope="module")
def minilm_embeddings():
    try:
        T.minilm_model_path()
    except T.TextEncoderError as error:
        pytest.skip(str(error))
    return T.encode_texts(NAMES, TextConfig())


def test_minilm_embeddings_are_normalized_and_distinct(minilm_embeddings):
    e = minilm_embeddings
    assert e.shape == (3, 384) and e.dtype == torch.float32
    torch.testing.assert_close(e.norm(dim=1), torch.ones(3))
    sim = e @ e.T
    assert (sim - torch.eye(3)).abs().max() < 0.95  # different names, different vectors


def test_minilm_matches_sentence_transformers(minilm_embeddings):
    st = pytest.importorskip("sentence_transformers")
    model = st.SentenceTransformer(str(T.minilm_model_path()), device="cpu")
    prompts = T.format_prompts(NAMES, TextConfig().prompt_template)
    reference = model.encode(prompts, convert_to_tensor=True, normalize_embeddings=True).float()
    torch.testing.assert_close(minilm_embeddings, reference, atol=1e-5, rtol=1e-5)


def test_mean_pool_ignores_padding_and_fully_masked_rows():
    tokens = torch.tensor([[[1.0, 2.0], [3.0, 4.0], [100.0, 100.0]], [[5.0, 5.0], [7.0, 7.0], [9.0, 9.0]]])
    mask = torch.tensor([[1, 1, 0], [0, 0, 0]])
    pooled = T.mean_pool(tokens, mask)
    torch.testing.assert_close(pooled, torch.tensor([[2.0, 3.0], [0.0, 0.0]]))
    torch.testing.assert_close(T.l2_normalize(pooled)[1], torch.zeros(2))


def test_prompt_template():
    assert T.format_prompts(["bed"], "a photo of a {name}.") == ["a photo of a bed."]
    with pytest.raises(ValueError, match="placeholder"):
        T.format_prompts(["bed"], "a photo")


def test_clip_text_encoder_matches_manual_projection(tiny_clip):
    from transformers import CLIPModel, CLIPTokenizer

    cfg = TextConfig(encoder="clip", clip_model=tiny_clip)
    e = T.encode_texts(NAMES, cfg)
    assert e.shape == (3, 24)
    torch.testing.assert_close(e.norm(dim=1), torch.ones(3))
    model = CLIPModel.from_pretrained(str(tiny_clip)).eval()
    tok = CLIPTokenizer.from_pretrained(str(tiny_clip))
    ids = tok(["a photo of a chair."], return_tensors="pt")
    with torch.no_grad():
        hidden = model.text_model(**ids).last_hidden_state[0]
        eos = int(ids["input_ids"][0].tolist().index(1))  # the eos token (id 1) is pooled
        manual = model.text_projection(hidden[eos])
    torch.testing.assert_close(e[0], manual / manual.norm(), atol=1e-5, rtol=1e-5)


def test_missing_models_give_clear_errors(tmp_path):
    with pytest.raises(T.TextEncoderError, match="--clip-model PATH"):
        T.encode_texts(NAMES, TextConfig(encoder="clip"))
    with pytest.raises(T.TextEncoderError, match="config.json missing"):
        T.encode_texts(NAMES, TextConfig(encoder="clip", clip_model=tmp_path))
    with pytest.raises(ValueError, match="no class names"):
        T.encode_texts([], TextConfig())


def test_vocabulary_cache_is_keyed_by_names_and_encoder(tiny_clip, tmp_path, monkeypatch):
    cfg = TextConfig(encoder="clip", clip_model=tiny_clip)
    first = T.load_or_encode_texts(NAMES, cfg, tmp_path)
    files = list(tmp_path.glob("text_clip_*.safetensors"))
    assert len(files) == 1
    calls = []
    monkeypatch.setattr(T, "encode_texts", lambda names, config: calls.append(names) or torch.zeros(len(names), 24))
    again = T.load_or_encode_texts(NAMES, cfg, tmp_path)
    assert calls == [] and torch.equal(first, again)  # read from the cache
    T.load_or_encode_texts(NAMES[:2], cfg, tmp_path)
    T.load_or_encode_texts(NAMES, TextConfig(encoder="clip", clip_model=tiny_clip, prompt_template="{name}"), tmp_path)
    assert len(calls) == 2 and len(list(tmp_path.glob("text_clip_*.safetensors"))) == 3
