"""Text and image-text embeddings: ``encoders`` (class names -> L2-normalized embeddings), ``vocabulary`` (the one
vocabulary type), ``prompt_ensemble`` (class names under several templates), ``teacher`` (the dense MaskCLIP
teacher of the visual-semantic loss).
"""

__all__ = ["encoders", "prompt_ensemble", "teacher", "vocabulary"]
