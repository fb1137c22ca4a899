"""Motion data, chapter 2: skeletons, clips, BVH, the A-MDM frame features and motion metrics.

* :mod:`~minimdm.motion.skeleton`: skeletons, rotations (quaternions, matrices, 6D), batched FK;
* :mod:`~minimdm.motion.data`: clips, the DeepMimic clips of ``pybullet_data``, datasets;
* :mod:`~minimdm.motion.bvh`: BVH reading and writing;
* :mod:`~minimdm.motion.features`: the A-MDM frame representation, normalizer, windows;
* :mod:`~minimdm.motion.metrics`: foot sliding, bone error, acceleration, diversity.
"""
