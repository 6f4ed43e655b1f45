"""The segmenter itself: numpy, scipy and (optionally) numba; never imports ROS.

One module per stage, each holding its numpy reference and its compiled (numba) kernel side by
side and registering them once in its row of the stage table (``stages.STAGES``, in frame
order; ``compiled.Stage`` and ``compiled.Twin``). The paper's stages: ``grid`` (radial grid,
candidates, rho~), ``lines`` (Algorithm 1 and the steep-line filter), ``length_factors`` (eq.
12), ``paciorek`` (the kernel, eq. 7), ``gp`` (the whole-frame GP and theta, eq. 14),
``predict`` (the posterior at the bin edges), ``labels`` (the label rule). Ours, each with a
``use_*`` switch: ``plateau``, ``anchor``, ``outliers`` (with the wide-terrain rule),
``coupled_surface`` (the ground on the borders between segments, a 2-D GP), ``structure``
(feet of vertical structures), ``free_space`` (feet the sensor saw under), ``surface`` (the
ground surface output), and the rules marked [ours] inside ``lines``, ``length_factors`` and
``labels``. ``segmenter`` runs them in order, ``result``
holds what it returns, ``params`` every tunable; ``compiled`` compiles and runs the twins;
``sensor_frame`` levels clouds not in the sensor frame.

Adding a stage, in an afternoon:

1. a module ``core/<stage>.py``: the numpy function (the reference) and, if it pays, the same
   as a loop, ``Twin('<name>', reference, compiled.kernel(loop), examples)`` beside them
   (``examples(dtype)``: tiny arguments of every signature a frame passes), and
   ``STAGES = (Stage('<stage>', 'ours', 'use_<stage>', (TWIN,)),)``;
2. ``use_<stage>`` and its numbers (units, ranges) in ``params.SegmenterParams``;
3. the module's ``STAGES`` into ``stages.STAGES`` at its place in the frame;
4. one call in ``GroundSegmenter._segment`` (or the stage helper it belongs to), behind
   ``STAGE.on(params)``.

warm_up compiles the new twin and test/test_stage_table.py checks its kernel against its
reference on real frames without further changes; unit tests of the stage go beside the others.
"""
