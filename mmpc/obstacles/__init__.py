"""The obstacles a plan is made around: their shape and where they go.

- :mod:`mmpc.obstacles.shape`: the obstacle ellipse (covering two vehicles, widened for a turned
  car), the normalised distance and clearance every reader of the shape uses, and the choice
  of the nearest vehicles;
- :mod:`mmpc.obstacles.prediction`: the predictions of their centres over the horizon.
"""
