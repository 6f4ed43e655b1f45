"""The segmenter itself: numpy, scipy and (optionally) numba; never imports ROS.

Paper parts: ``grid`` (radial grid, candidates, rho~), ``lines`` (Algorithm 1), ``gp`` (Paciorek
kernel, whole-frame marginal likelihood, prediction). ``segmenter`` composes them.
"""
