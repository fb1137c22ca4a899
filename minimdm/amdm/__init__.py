"""A-MDM (Shi et al. 2024), chapters 3 and 4: the auto-regressive motion diffusion model.

* :mod:`~minimdm.amdm.models`: the MLP denoiser and the two baselines (MSE regressor, MVAE);
* :mod:`~minimdm.amdm.train`: scheduled-sampling training of all three (A-MDM §3.2);
* :mod:`~minimdm.amdm.sampling`: a checkpoint's Sampler and rollouts, frame after frame (§3.1);
* :mod:`~minimdm.amdm.evaluation`: the evaluation protocol of A-MDM §7.3.
"""
