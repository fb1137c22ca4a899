"""CAMDM (Chen et al. 2024, "Taming Diffusion Probabilistic Models for Character Control"),
chapter 9: a conditional auto-regressive motion diffusion model and its run-time controller.

* :mod:`~minimdm.camdm.data`: the frames of a window in the frame of its last past frame (root
  position + 6D local rotations), the trajectory condition (c_rv, c_ro), the training windows;
* :mod:`~minimdm.camdm.model`: the transformer denoiser of eq. 1 with separate condition tokens
  (and the ablations: one fused token, an MLP backbone);
* :mod:`~minimdm.camdm.train_config`, :mod:`~minimdm.camdm.train`: eqs. 2-4 and past-motion
  dropout (``minimdm camdm train``);
* :mod:`~minimdm.camdm.sampling`: CFG on past motion (eq. 5) as a step rule of the one reverse
  chain, :func:`minimdm.diffusion.reverse_chain`;
* :mod:`~minimdm.camdm.trajectory`: the spring, blended and extended (HFTE) trajectories;
* :mod:`~minimdm.camdm.controller`: the run-time controller, a plain loop over frames that
  re-plans when it must;
* :mod:`~minimdm.camdm.classifier`: the style classifier of 60-frame clips and the Fréchet
  distance of its features (``minimdm camdm classifier``).
"""
