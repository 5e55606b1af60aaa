"""Registration of a splat onto its scene's labelled mesh: the similarity ``world_from_splat`` that
``seggaussian align`` writes for ``--transform`` (never applied silently).
"""

__all__ = ["registration"]
