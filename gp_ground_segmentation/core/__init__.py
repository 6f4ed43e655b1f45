"""The segmenter itself: numpy, scipy and (optionally) numba; never imports ROS.

Paper parts: ``grid`` (radial grid, candidates, rho~), ``lines`` (Algorithm 1), ``gp`` (Paciorek
kernel, whole-frame marginal likelihood, prediction). Our additions, each switchable:
``additions`` (elevated plateaus, the r = 0 anchor, leave-one-out outlier rejection).
``segmenter`` composes them; ``params`` holds every tunable.
"""
