"""The batch non-holonomic trajectory optimizer, one module per job:

- :mod:`mmpc.solver.config`: :class:`~mmpc.solver.config.OptimizerConfig`, its settings;
- :mod:`mmpc.solver.basis`: the Bernstein basis and its derivatives; :mod:`mmpc.solver.operators`: the cached KKT
  inverses; :mod:`mmpc.solver.trig`: sin, cos and atan2 as short polynomials for the compiled iterations;
- :mod:`mmpc.solver.iterations`: the alternating-minimisation iterations, pure tensor functions;
- :mod:`mmpc.solver.checks`: input checks of problems and warm starts, non-finite replacement;
- :mod:`mmpc.solver.execution`: eager or compiled, tiles and padding, CUDA graphs;
- :mod:`mmpc.solver.optimizer`: :class:`~mmpc.solver.optimizer.BatchOptimizer`, the module that ties them.

:mod:`mmpc` exports both classes. This file imports
nothing: :mod:`mmpc.solver.operators` reads the config, and the optimizer reads the operators.
"""
