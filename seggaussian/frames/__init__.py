"""Moving splats between frames: a splat trained by another tool, in that tool's frame, into the scene's (mesh) frame.

The package owns the similarity transforms (``Similarity``), moving ``Gaussians`` by one (``transform_gaussians``:
means, covariances, opacities kept, view-dependent SH colour rotated), the real-SH rotation of the 3DGS basis
(``rotate_sh``), axis-letter frames (``axes_to_rdf``), and reading what users give as ``--transform`` /
``--from-frame`` (``load_transform``, ``resolve_transform``), including recomputing gsplat's normalization from a
COLMAP model. numpy only (no torch).

Conventions
-----------
- Direction: every transform is ``world_from_splat``: it maps the splat file's coordinates to the scene's (mesh)
  frame, ``x_world = scale * rotation @ x_splat + translation``. The world frame's axes are named RDF (x right,
  y down, z forward: OpenCV/COLMAP).
- Composition: ``a.compose(b)`` is ``a o b`` (``b`` first). A ``{"chain": [s1, s2, ...]}`` applies ``s1`` to the
  splat first, then ``s2``...: ``world_from_splat = s_n o ... o s1``. ``--from-frame`` is applied before
  ``--transform`` (to the splat's raw coordinates).
- Reflections (det -1, e.g. a left-handed ``RUF`` source) are allowed. Gaussians are rotated by ``Q = -M`` (a proper
  rotation giving the same covariance ``M S M^T``) and SH band ``l`` is additionally multiplied by ``(-1)^l``, so
  that the colour seen along ``M d`` after equals the colour seen along ``d`` before.
- Scale: means scale, log-scales grow by ``log(scale)``; opacity and SH are scale-free.

Which tool exports in which frame
---------------------------------
- Inria 3DGS ``train.py``: the COLMAP world, unchanged (its normalization only sets the densification extent). For
  a COLMAP model registered to the scan (ScanNet++ ``dslr/colmap``), no transform is needed.
- gsplat ``examples/simple_trainer.py`` (``normalize_world_space=True``, the default): a normalized frame computed
  from the COLMAP model: ``gsplat:COLMAP_DIR`` recomputes and inverts it (``gsplat-legacy:`` for gsplat < 1.5.2,
  which had no upside-down flip). With ``--normalize_world_space False``: the COLMAP world.
- nerfstudio splatfacto (``ns-export gaussian-splat``): the dataparser's auto-oriented, centred and scaled frame; the
  run's ``dataparser_transforms.json`` maps the input data's world to it; give that file (it is inverted).
  Its SH are not rotated by nerfstudio (PR #2951 was left open for that reason); ``transform_gaussians`` rotates them.
  For ScanNet++ the nerfstudio ``transforms.json`` world is itself the mesh frame with x and y swapped and z negated
  (the ScanNet++ toolkit's conversion), i.e. ``frame:DRB``; a splatfacto model trained on it is brought home by
  ``{"chain": ["dataparser_transforms.json", "frame:DRB"]}``.
- Viewers and engines: three.js/OpenGL exports are ``RUB``, Unity ``RUF`` (left-handed); use ``--from-frame``.
"""

from seggaussian.frames.axes import axes_to_rdf
from seggaussian.frames.sh_rotation import rotate_sh
from seggaussian.frames.similarity import Similarity, transform_gaussians
from seggaussian.frames.transform_spec import FrameTransform, TransformSpecError, load_transform, resolve_transform

__all__ = [
    "FrameTransform",
    "Similarity",
    "TransformSpecError",
    "axes_to_rdf",
    "load_transform",
    "resolve_transform",
    "rotate_sh",
    "transform_gaussians",
]
