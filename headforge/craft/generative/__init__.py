"""HeadCraft part 2 (seed 002, §3.2, A.2, B): generative models over UV displacement maps.

- :mod:`~headforge.craft.generative.data` -- the training set: maps of a registered scan set,
  faces replaced by the neutral scan's (A.2), split by identity;
- :mod:`~headforge.craft.generative.stylegan2` -- StyleGAN2 (the paper's model);
- :mod:`~headforge.craft.generative.pca`, :mod:`~headforge.craft.generative.vae`,
  :mod:`~headforge.craft.generative.vqvae` -- the baselines of Tables 1-2;
- :mod:`~headforge.craft.generative.train` -- run folders, training, checkpoints, resume;
- :mod:`~headforge.craft.generative.sample` -- maps, seam post-processing, meshes, sheets;
- :mod:`~headforge.craft.generative.evaluate` -- MMD / COV / 1-NNA / JSD and the memorisation check.

Maps: (H, W, 3) metres in canonical axes (y up, face toward +z); models see them / 2 cm.
"""
