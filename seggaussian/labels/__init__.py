"""Labels of Gaussians: the transfer from a scene's labelled points (nearest point within a gate; ``vote`` is the
compared alternative, ``scoring`` the check against the mesh, ``occlusion`` the points no view sees, which give no
label), oracle Gaussians sampled on the labelled mesh with
their true class, the placement check that refuses a splat not sitting on its mesh, and the label palette.
``config`` holds the transfer's and the oracle sampler's frozen configurations.
"""

__all__ = ["config", "occlusion", "oracle", "palette", "placement", "scoring", "transfer", "vote"]
