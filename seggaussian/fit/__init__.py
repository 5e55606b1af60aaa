"""Fitting 3D Gaussians to a scene's posed images on the CPU (3D Gaussian Splatting, Kerbl et al. 2023).

``optimize.fit_scene`` is the loop; ``config`` its frozen configuration and presets; ``views`` the images as
tensors (and mesh depth); ``initialize`` the initial Gaussians; ``params`` the trainable tensors and Adam state;
``densify`` adaptive density control; ``losses`` L1, SSIM and PSNR. Rendering is ``seggaussian.render``.
"""

__all__ = ["config", "densify", "initialize", "losses", "optimize", "params", "views"]
