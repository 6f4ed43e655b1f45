"""The segmenter itself: numpy, scipy and (optionally) numba; never imports ROS.

Paper parts: ``grid`` (radial grid, candidates, rho~), ``lines`` (Algorithm 1), ``gp`` (Paciorek
kernel, whole-frame marginal likelihood, prediction). Our additions, each switchable:
``additions`` (elevated plateaus, the r = 0 anchor, leave-one-out outlier rejection with its
wide-terrain rule, chord slopes, length-factor smoothing, the cross-slope threshold),
``structure`` (feet of vertical structures), ``sensor_frame`` (clouds not in the sensor frame),
``surface`` (the ground surface output). ``segmenter`` composes them; ``params`` holds every
tunable; ``compiled`` and ``gp_compiled`` hold the numba kernels.
"""
