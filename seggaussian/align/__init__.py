"""Registration of a splat onto its scene's labelled mesh: the similarity ``world_from_splat`` that
``seggaussian align`` writes for ``--transform`` (never applied silently). ``target`` holds what an alignment is
given and measured against (its configuration, the scene's mesh, the distances and placement); ``registration``
the search (features, RANSAC, ICP with scale, scoring), its result and the command's one call.
"""

__all__ = ["registration", "target"]
