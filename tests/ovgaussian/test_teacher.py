"""Dense MaskCLIP teacher on a tiny randomly initialized CLIP: shapes, value path by hand, caching."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from ovgaussian.text import teacher as TT
from ovgaussian.text.encoders import TextEncoderError
from ovgaussian.run.config import TeacherConfig


@pytest.fixture(scope="module")
def clip_model():
    from transformers import CLIPConfig, CLIPModel

    config = CLIPConfig(
        text_config=dict(hidden_size=32, intermediate_size=48, num_hidden_layers=1, num_attention_heads=2,
                         vocab_size=60, max_position_embeddings=16, bos_token_id=0, eos_token_id=1, pad_token_id=1),
        vision_config=dict(hidden_size=32, intermediate_size=48, num_hidden_layers=3, num_attention_heads=4,
                           image_size=32, patch_size=8),
        projection_dim=24,
    )
    torch.manual_seed(0)
    return CLIPModel(config).eval()


def rgb_image(h=30, w=45, seed=0):
    return np.random.default_rng(seed).integers(0, 256, size=(h, w, 3), dtype=np.uint8)


def hand_written_value_path(model, pixels, residual_mlp):
    """MaskCLIP last block written out with the raw weights (q and k never used)."""
    vision = model.vision_model
    with torch.no_grad():
        out = vision(pixel_values=pixels, interpolate_pos_encoding=True, output_hidden_states=True)
        x = out.hidden_states[-2]  # input tokens of the last encoder layer
        last = vision.encoder.layers[-1]
        ln1 = F.layer_norm(x, (x.shape[-1],), last.layer_norm1.weight, last.layer_norm1.bias, last.layer_norm1.eps)
        v = F.linear(ln1, last.self_attn.v_proj.weight, last.self_attn.v_proj.bias)
        v = F.linear(v, last.self_attn.out_proj.weight, last.self_attn.out_proj.bias)
        if residual_mlp:
            y = x + v
            ln2 = F.layer_norm(y, (y.shape[-1],), last.layer_norm2.weight, last.layer_norm2.bias, last.layer_norm2.eps)
            h = F.linear(ln2, last.mlp.fc1.weight, last.mlp.fc1.bias)
            h = h * torch.sigmoid(1.702 * h)  # quick_gelu of CLIP
            y = y + F.linear(h, last.mlp.fc2.weight, last.mlp.fc2.bias)
        else:
            y = v
        pln = vision.post_layernorm
        y = F.layer_norm(y, (y.shape[-1],), pln.weight, pln.bias, pln.eps)
        return y @ model.visual_projection.weight.T


@pytest.mark.parametrize("residual_mlp", [True, False])
def test_patch_features_equal_the_hand_written_value_path(clip_model, residual_mlp):
    assert clip_model.config.vision_config.hidden_act == "quick_gelu"
    teacher = TT.DenseTeacher(clip_model, TeacherConfig(short_side=32, residual_mlp=residual_mlp))
    rgb = rgb_image()
    features = teacher.compute_patch_features(rgb)
    assert features.image_size == (30, 45)
    assert TT.resized_shape(30, 45, 32, 8) == (32, 48)
    assert features.patch_features.shape == (4, 6, 24)
    pixels = TT.preprocess_image(rgb, 32, 48)
    expected = hand_written_value_path(clip_model, pixels, residual_mlp)[0, 1:].reshape(4, 6, 24)
    torch.testing.assert_close(features.patch_features, expected, atol=1e-5, rtol=1e-5)
    # and it is not the ordinary last layer (the q-k attention really is skipped)
    with torch.no_grad():
        ordinary = clip_model.vision_model(pixel_values=pixels, interpolate_pos_encoding=True).last_hidden_state
        ordinary = clip_model.visual_projection(clip_model.vision_model.post_layernorm(ordinary))[0, 1:]
    assert (ordinary.reshape(4, 6, 24) - features.patch_features).abs().max() > 1e-3


def test_preprocess_normalizes_with_clip_statistics():
    rgb = np.zeros((4, 4, 3), np.uint8)
    rgb[..., 0] = 255
    x = TT.preprocess_image(rgb, 4, 4)
    assert x.shape == (1, 3, 4, 4)
    torch.testing.assert_close(x[0, :, 0, 0], torch.tensor([(1 - TT.CLIP_MEAN[0]) / TT.CLIP_STD[0],
                                                            -TT.CLIP_MEAN[1] / TT.CLIP_STD[1],
                                                            -TT.CLIP_MEAN[2] / TT.CLIP_STD[2]]))
    with pytest.raises(ValueError, match=r"\[H, W, 3\]"):
        TT.preprocess_image(np.zeros((4, 4), np.uint8), 4, 4)


def test_features_are_cached_once_per_view(clip_model, tmp_path, monkeypatch):
    teacher = TT.DenseTeacher(clip_model, TeacherConfig(short_side=32))
    rgb = rgb_image(seed=1)
    first = teacher.cached_patch_features(rgb, tmp_path, "scene__view")
    assert len(list(tmp_path.rglob("*.safetensors"))) == 1

    def fail(_):
        raise AssertionError("recomputed although cached")

    monkeypatch.setattr(teacher, "compute_patch_features", fail)
    again = teacher.cached_patch_features(rgb, tmp_path, "scene__view")
    assert torch.equal(first.patch_features, again.patch_features) and again.image_size == (30, 45)
    other = TT.DenseTeacher(clip_model, TeacherConfig(short_side=40))
    assert other.cache_key != teacher.cache_key  # another input size gets another cache folder


def test_sampling_at_pixel_centres_matches_upsampling():
    grid = torch.randn(4, 6, 5)
    full = TT.upsample_patch_features(grid, (30, 45))
    assert full.shape == (30, 45, 5)
    v, u = torch.meshgrid(torch.arange(30), torch.arange(45), indexing="ij")
    pixels = torch.stack([u.reshape(-1), v.reshape(-1)], 1)
    sampled = TT.sample_patch_features(grid, pixels, (30, 45))
    torch.testing.assert_close(sampled, full.reshape(-1, 5), atol=1e-5, rtol=1e-5)
    # a grid the same size as the image is read exactly at the pixel centres
    same = torch.randn(3, 4, 2)
    v, u = torch.meshgrid(torch.arange(3), torch.arange(4), indexing="ij")
    exact = TT.sample_patch_features(same, torch.stack([u.reshape(-1), v.reshape(-1)], 1), (3, 4))
    torch.testing.assert_close(exact, same.reshape(-1, 2))


def test_missing_clip_is_a_clear_error(tmp_path):
    with pytest.raises(TextEncoderError, match="--clip-model PATH"):
        TT.DenseTeacher.from_config(TeacherConfig())
    with pytest.raises(TextEncoderError, match="config.json missing"):
        TT.DenseTeacher.from_config(TeacherConfig(clip_model=tmp_path))


def test_from_config_loads_a_saved_model(clip_model, tmp_path):
    clip_model.save_pretrained(str(tmp_path / "clip"))
    teacher = TT.DenseTeacher.from_config(TeacherConfig(clip_model=tmp_path / "clip", short_side=32))
    direct = TT.DenseTeacher(clip_model, TeacherConfig(short_side=32))
    rgb = rgb_image(seed=2)
    torch.testing.assert_close(teacher.compute_patch_features(rgb).patch_features,
                               direct.compute_patch_features(rgb).patch_features)
    assert teacher.feature_dim == 24


class _Layer4x(torch.nn.Module):
    """The transformers 4.x ``CLIPEncoderLayer.forward`` signature (both masks required, tuple out)."""

    def forward(self, hidden_states, attention_mask, causal_attention_mask, output_attentions=False):
        assert attention_mask is None and causal_attention_mask is None
        return (hidden_states + 1.0,)


class _Layer5x(torch.nn.Module):
    """The transformers 5.x signature (``attention_mask`` plus keyword arguments, tensor out)."""

    def forward(self, hidden_states, attention_mask, **kwargs):
        assert attention_mask is None and not kwargs
        return hidden_states + 1.0


def test_encoder_layer_masks_fit_both_transformers_signatures():
    assert TT.encoder_layer_masks(_Layer4x()) == {"attention_mask": None, "causal_attention_mask": None}
    assert TT.encoder_layer_masks(_Layer5x()) == {"attention_mask": None}
    x = torch.zeros(1, 3, 2)
    for layer in (_Layer4x(), _Layer5x()):
        out = layer(x, **TT.encoder_layer_masks(layer))
        assert torch.equal(out[0] if isinstance(out, tuple) else out, x + 1.0)


def test_layer_loop_of_a_tiny_clip_vision_model_equals_its_own_forward():
    """The teacher's layer loop on the installed transformers' CLIPVisionModel (random weights, no
    download) gives the hidden states of the model's own forward, layer by layer."""
    from transformers import CLIPVisionConfig, CLIPVisionModel

    torch.manual_seed(1)
    model = CLIPVisionModel(CLIPVisionConfig(hidden_size=16, intermediate_size=24, num_hidden_layers=3,
                                             num_attention_heads=2, image_size=16, patch_size=8)).eval()
    vision = getattr(model, "vision_model", model)  # 4.x wraps the tower, 5.x is flat
    pixels = TT.preprocess_image(rgb_image(16, 24), 16, 24)
    with torch.no_grad():
        own = vision(pixel_values=pixels, interpolate_pos_encoding=True, output_hidden_states=True).hidden_states
        hidden = vision.pre_layrnorm(vision.embeddings(pixels, interpolate_pos_encoding=True))
        torch.testing.assert_close(hidden, own[0])
        for i, layer in enumerate(vision.encoder.layers):
            hidden = layer(hidden, **TT.encoder_layer_masks(layer))
            hidden = hidden[0] if isinstance(hidden, tuple) else hidden
            torch.testing.assert_close(hidden, own[i + 1], atol=1e-6, rtol=1e-5)
        tokens = TT.maskclip_tokens(vision, torch.nn.Linear(16, 5, bias=False), pixels, residual_mlp=True)
    assert tokens.shape == (1, 1 + 2 * 3, 5) and torch.isfinite(tokens).all()
