"""AAMDM (Qiao et al. 2024), chapter 8: few DD-GAN steps draft a sample, few diffusion steps
polish it, in an embedded pose space.

* :mod:`~minimdm.aamdm.nets`: the DD-GAN generator and the step-conditioned discriminator;
* :mod:`~minimdm.aamdm.model`: the AAMDM schedule, the model (generator + polisher) and its
  sampler, a pair of step rules on the one reverse chain of :mod:`minimdm.diffusion`;
* :mod:`~minimdm.aamdm.train`: adversarial training of the generator (Algorithm 1) and the
  polisher;
* :mod:`~minimdm.aamdm.motion`: the pose embedding (future-trajectory features + autoencoder)
  and the motion model; :mod:`~minimdm.aamdm.motion_train` trains it
  (``python -m minimdm.aamdm train configs/aamdm.yaml``);
* :mod:`~minimdm.aamdm.eval`: rollouts and eq. 13 guidance on motion.
"""
